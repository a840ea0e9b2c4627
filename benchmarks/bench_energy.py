"""The energy budget of the dam break and the dragon scene (issue 17), per frame: kinetic, potential
(from the lowest wall point) and their sum, in J, and the largest specific energy of one particle
(J/kg) against the largest any particle had at the start, and the 99th percentile and highest particle
heights against the release height:

    .venv/bin/python benchmarks/bench_energy.py [--scenes dam_break,dragon] [--spacing-factor 1.6]
                                                [--solver sph] [--frames N]

Each scene runs through the pipeline (configs/<scene>.yaml, the spacing multiplied by the factor to
keep it short). Without numerical energy creation the total can only fall (viscosity, the walls'
no-slip, artificial viscosity); one particle can exceed its own start energy only by work the pressure
does on it (a splash is physical when the total still falls and the gain is a pressure transfer, as in
Ritter's dam-break front at 2 sqrt(g H)). Writes benchmarks/results/energy.json (energy_<solver>.json for
another solver)."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pipeline  # noqa: E402
from stages.common.formats import ParticleMeta, load_particle_frame  # noqa: E402
from stages.common.sdf import SDFGrid  # noqa: E402

G = 9.81


def budget(scene: str, factor: float, solver: str, frames: int | None) -> dict:
    import yaml
    cfg = yaml.safe_load((ROOT / "configs" / f"{scene}.yaml").read_text())
    spacing = float(cfg["fluid"]["spacing"]) * factor
    same = cfg["stages"]["simulate"].get("use") == solver  # another solver: the config's section replaced whole
    over = [f"fluid.spacing={spacing}", f"simulate.use={solver}" if same else f"simulate={{use: {solver}}}",
            "outputs=[particles, sdf]"]
    if frames:
        over.append(f"scene.frames.count={frames}")
    report = pipeline.run(ROOT / "configs" / f"{scene}.yaml", overrides=tuple(over),
                          cache_dir=ROOT / "benchmarks" / ".cache", out_dir=ROOT / "out" / f"bench_energy_{scene}",
                          progress=False)
    out = Path(report.outputs["particles"])
    meta = ParticleMeta.load(out)
    sdf = SDFGrid.load(Path(report.outputs["sdf"]))
    mpu = meta.meters_per_unit
    axis = 2 if meta.up_axis == "Z" else 1
    floor = float(sdf.origin[axis]) * mpu
    rows = []
    e_spec0 = None
    for f in range(meta.frame_count):
        fr = load_particle_frame(out, f)
        z = fr.x[:, axis] * mpu
        v2 = np.einsum("ij,ij->i", fr.v, fr.v) * mpu * mpu
        spec = 0.5 * v2 + G * (z - floor)
        if e_spec0 is None:
            e_spec0 = float(spec.max())
            z_top0 = float(z.max())
        rows.append({"frame": f, "t": f / meta.fps, "kinetic": float(0.5 * meta.mass * v2.sum()),
                     "potential": float(meta.mass * G * (z - floor).sum()),
                     "specific_max": float(spec.max()), "specific_max_over_start": float(spec.max()) / e_spec0,
                     "z_p99_over_release_top": float((np.percentile(z, 99) - floor) / (z_top0 - floor)),
                     "z_max_over_release_top": float((z.max() - floor) / (z_top0 - floor)),
                     "particles": int(len(z))})
        rows[-1]["total"] = rows[-1]["kinetic"] + rows[-1]["potential"]
    total0 = rows[0]["total"]
    return {"scene": scene, "solver": solver, "spacing": spacing, "particles": rows[0]["particles"],
            "total_max_over_start": max(r["total"] for r in rows) / total0,
            "total_end_over_start": rows[-1]["total"] / total0,
            "specific_max_over_start": max(r["specific_max_over_start"] for r in rows),
            "z_max_over_release_top": max(r["z_max_over_release_top"] for r in rows),
            "frames": rows}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="dam_break,dragon")
    ap.add_argument("--spacing-factor", type=float, default=1.6)
    ap.add_argument("--solver", default="sph")
    ap.add_argument("--frames", type=int, default=None)
    a = ap.parse_args()
    results = []
    for scene in a.scenes.split(","):
        r = budget(scene, a.spacing_factor, a.solver, a.frames)
        results.append(r)
        print(f"{scene} ({r['particles']} particles, {a.solver}): total energy max/start {r['total_max_over_start']:.3f}, "
              f"end/start {r['total_end_over_start']:.3f}; one particle's specific energy up to "
              f"{r['specific_max_over_start']:.2f} x the largest at the start; highest particle at "
              f"{r['z_max_over_release_top']:.2f} x the release height", flush=True)
        for row in r["frames"][:: max(1, len(r["frames"]) // 12)]:
            print(f"  t {row['t']:.2f} s  KE {row['kinetic']:9.2f} J  PE {row['potential']:9.2f} J  total "
                  f"{row['total'] / r['frames'][0]['total']:.3f}  e_max {row['specific_max_over_start']:.2f}  "
                  f"z99 {row['z_p99_over_release_top']:.2f}  zmax {row['z_max_over_release_top']:.2f}", flush=True)
    name = "energy.json" if a.solver == "sph" else f"energy_{a.solver}.json"
    (ROOT / "benchmarks" / "results" / name).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
