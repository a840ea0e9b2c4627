"""SPH against MPS on the Martin & Moyce dam break: runs the study configs/compare_sph_mps.yaml (one
scene, simulate.use swept over sph and mps, through the normal cache), then reads each variant's
particle frames and plots the surge front Z/a against T = t sqrt(2 g / a) for both solvers against the
experiment (../shared/reference/martin_moyce_1952.csv), with each solver's timings in the legend.

    .venv/bin/python benchmarks/compare_sph_mps.py [--cache DIR] [--out DIR] [--workers 1]

Writes benchmarks/results/compare_sph_mps.json and benchmarks/results/images/compare_sph_mps.png.
The machine is shared: timings are noisy; the two solvers ran in the same session, one after the other
(--workers 1), so their ratio is the figure to quote."""
from __future__ import annotations

import argparse
import csv
import json
import os
from pathlib import Path

import numpy as np

from pipeline.study import load_study, run_study
from stages.common.formats import ParticleMeta, load_particle_frame

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "configs" / "compare_sph_mps.yaml"
REFERENCE = ROOT.parent / "shared" / "reference" / "martin_moyce_1952.csv"
if not REFERENCE.is_file():  # the copy the tests carry
    REFERENCE = ROOT / "tests" / "data" / "martin_moyce_1952.csv"
G = 9.81


def martin_moyce() -> np.ndarray:
    rows = csv.DictReader(line for line in REFERENCE.read_text().splitlines() if not line.startswith("#"))
    return np.array([(float(r["T"]), float(r["Z_over_a"])) for r in rows if r["series"] == "a_2.25in"])


def column(study_path: Path) -> tuple[float, float, float]:
    """(back wall x, column width a, spacing l0) from the study's `set` overrides."""
    sets = dict(s.split("=", 1) for s in load_study(study_path).set)
    import yaml
    box = yaml.safe_load(sets["fluid.emitters.0.box"])
    return float(box["min"][0]), float(box["max"][0] - box["min"][0]), float(sets["fluid.spacing"])


def surge_front(particles: Path, x_back: float, a: float, l0: float) -> list[tuple[float, float]]:
    """(T, Z/a) per frame: the front is the third-furthest particle (two lone droplets ignored), plus
    half a spacing, as in tests/test_sph_dam_break.py."""
    meta = ParticleMeta.load(particles)
    scale = np.sqrt(2 * G / a)
    out = []
    for f in range(meta.frame_count):
        x = np.sort(load_particle_frame(particles, f).x[:, 0])
        out.append((float(f / meta.fps * scale), float((x[-3] + 0.5 * l0 - x_back) / a)))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--cache", type=Path, default=None, help="pipeline cache (default: configs/.pipeline)")
    ap.add_argument("--out", type=Path, default=None, help="study output (default: configs/out/compare_sph_mps)")
    ap.add_argument("--workers", type=int, default=1)
    a = ap.parse_args()
    results, out_root = run_study(STUDY, cache_dir=a.cache, out_dir=a.out, workers=a.workers)
    x_back, width, l0 = column(STUDY)
    ref = martin_moyce()
    summary = {"study": str(STUDY.relative_to(ROOT)), "column_width_a": width, "spacing": l0, "solvers": {}}
    for r in results:
        solver = r.overrides["simulate.use"]
        particles = Path(r.out) / "particles"
        meta = ParticleMeta.load(particles)
        front = surge_front(particles, x_back, width, l0)
        T, Z = np.array(front).T
        keep = ref[:, 0] <= T.max()
        z_at_ref = np.interp(ref[keep, 0], T, Z)
        rel = (z_at_ref - ref[keep, 1]) / ref[keep, 1]
        st = meta.stats
        summary["solvers"][solver] = {
            "particles": st["particles"], "steps": st["steps"], "mean_dt": st["mean_dt"],
            "simulate_seconds": r.seconds, **st["summary"],
            "particle_steps_per_s": st["particles"] * st["steps"] / max(st["wall_seconds"], 1e-9),
            "surge_front": front,
            "vs_martin_moyce": {"T": ref[keep, 0].tolist(), "Z_ref": ref[keep, 1].tolist(), "Z_sim": z_at_ref.tolist(),
                                "relative_error": rel.tolist(), "max_abs_relative_error": float(np.abs(rel).max())},
        }
        print(f"{solver}: {st['particles']} particles, {st['steps']} steps, {st['summary']['ms_per_step']:.1f} ms/step, "
              f"{st['summary']['wall_seconds_per_simulated_second']:.0f} s per simulated s; surge front vs Martin & Moyce "
              f"(T <= {T.max():.1f}): max |rel| {np.abs(rel).max():.3f}, per point {np.round(rel, 3).tolist()}")
    res = ROOT / "benchmarks" / "results"
    (res / "images").mkdir(parents=True, exist_ok=True)
    (res / "compare_sph_mps.json").write_text(json.dumps(summary, indent=1))
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=130)
    ax.plot(ref[:, 0], ref[:, 1], "ks", ms=5, label="Martin & Moyce 1952 (a = 2.25 in)")
    for solver, style in (("sph", "C0o-"), ("mps", "C3^-")):
        s = summary["solvers"].get(solver)
        if s is None:
            continue
        T, Z = np.array(s["surge_front"]).T
        ax.plot(T, Z, style, ms=3, lw=1.2, label=f"{solver.upper()}: {s['ms_per_step']:.1f} ms/step, dt {1e3 * s['mean_dt']:.2f} ms, "
                f"{s['wall_seconds_per_simulated_second']:.0f} s/sim s")
    tmax = max(np.array(s["surge_front"])[:, 0].max() for s in summary["solvers"].values())
    ax.set_xlim(0, tmax * 1.02)
    zmax = max(np.array(s["surge_front"])[:, 1].max() for s in summary["solvers"].values())
    ax.set_ylim(0.8, max(zmax, ref[ref[:, 0] <= tmax, 1].max()) * 1.05)
    ax.set_xlabel("T = t sqrt(2 g / a)")
    ax.set_ylabel("surge front Z / a")
    n = next(iter(summary["solvers"].values()))["particles"]
    ax.set_title(f"dam break, column a x 2a, {n} particles (configs/compare_sph_mps.yaml)\n"
                 "timings from one run on a shared 2-core machine", fontsize=9)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(res / "images" / "compare_sph_mps.png")
    print(f"wrote {res / 'compare_sph_mps.json'} and {res / 'images' / 'compare_sph_mps.png'}; study report in {out_root}")


if __name__ == "__main__":
    main()
