"""SPlisHSPlasH WCSPH and DFSPH as points on the Martin & Moyce accuracy-against-time plot (issue 20).

    python benchmarks/peers_accuracy_plot.py [--study-json PATH] [--methods dfsph,wcsph]

Ours: the study configs/studies/accuracy_vs_time.yaml, run here first (through the cache: variants already
computed are not re-run, so their times are the ones recorded when they ran) unless ``--study-json`` names a
finished study.json. Peer: SPlisHSPlasH (splishsplash_run.py: volume maps, CFL steps) on the same scene
(martin_moyce.yaml: a = 0.25 m column, H = 2a, 1.25 x 0.25 x 0.75 m tank, mu = 0.001 Pa s, 0.4 s sampled at
60 fps) at the study's spacings, its DFSPH at our DFSPH's CFL number, largest step and tolerances, its WCSPH
(stiffness 50,000, exponent 7) at our WCSPH's CFL number and at most 0.5 ms. The same metric,
stages.simulate.validation:surge_front_error, on a meta.json written from its per-frame extents; its column
starts one spacing off the back wall (splishsplash_run.py), so its front is measured from there. Its time:
the stepping alone (its volume maps, cached between runs of the same spacing, and its first steps excluded),
while ours is the whole simulate stage (set-up included): the comparison leans towards the peer.

Writes benchmarks/results/peers_accuracy.json and benchmarks/results/images/accuracy_vs_time_peers.png."""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path

import yaml

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(HERE))

from bench_peers import run_splishsplash  # noqa: E402

STUDY = ROOT / "configs" / "studies" / "accuracy_vs_time.yaml"


def peer_point(method: str, spacing: float, base: dict, metric: dict) -> dict:
    from stages.simulate import validation
    from stages.simulate.dfsph import DFSPHParams
    from stages.simulate.sph import SPHParams

    fr = base["scene"]["frames"]
    wall = base["walls"][0]
    size, centre = wall["size"], wall["center"]
    lo = [centre[0] - size[0] / 2, centre[1] - size[1] / 2, centre[2]]
    hi = [centre[0] + size[0] / 2, centre[1] + size[1] / 2, centre[2] + size[2]]
    box = base["fluid"]["emitters"][0]["box"]
    if method == "dfsph":
        p = DFSPHParams()
        kw = dict(cfl_factor=p.cfl / 0.4, dt_max=p.dt_max, max_error=100 * p.max_density_error,
                  max_error_v=100 * p.max_divergence_error)
    else:
        kw = dict(cfl_factor=SPHParams().cfl / 0.4, dt_max=0.0005, dt=0.0005, stiffness=50000)
    gap = 1.0
    r = run_splishsplash({"tank_lo": lo, "tank_hi": hi, "fluid_lo": box["min"], "fluid_hi": box["max"],
                          "spacing": spacing, "method": method, "stop": (fr["count"] - 1) / fr["fps"] + 1e-6,
                          "fps": fr["fps"], "viscosity": base["effects"]["viscosity"]["mu"], "wall_gap": gap, **kw})
    if "skipped" in r:
        return {"method": method, "spacing": spacing, **r}
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "particles").mkdir()
        meta = {"spacing": spacing, "fps": fr["fps"], "meters_per_unit": 1.0,
                "stats": {"extent_max": [f["extent_max"] for f in r["frames"]]}}
        (Path(tmp) / "particles" / "meta.json").write_text(json.dumps(meta))
        args = dict(metric["args"], back_wall=metric["args"]["back_wall"] + gap * spacing)
        err = validation.surge_front_error(Path(tmp), study_dir=STUDY.parent, **args)
    r.pop("frames")
    return {"method": method, "spacing": spacing, "surge_front_error": err, "seconds": r["wall_s"], **r}


def read_study_md(path: Path) -> list[dict]:
    """The rows of a study.md table as study.json results (overrides, seconds, metrics)."""
    rows = [ln.strip().strip("|").split("|") for ln in path.read_text().splitlines() if ln.startswith("|")]
    head = [c.strip() for c in rows[0]]
    out = []
    for r in rows[2:]:
        cells = dict(zip(head, (c.strip() for c in r)))
        out.append({"overrides": {"fluid.spacing": float(cells["fluid.spacing"]), "simulate.use": cells["simulate.use"]},
                    "seconds": float(cells["simulate_seconds"]),
                    "metrics": {k: float(v) for k, v in cells.items() if k in ("surge_front_error", "density_error")}})
    return out


def blew_up(r: dict) -> bool:
    """A surge front error above 100 % (the front more than twice the experiment's): the fluid left the tank."""
    return r.get("surge_front_error", 0.0) > 1.0


def plot(ours: list[dict], peers: list[dict], out: Path) -> None:
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=120)
    for solver in ("sph", "dfsph", "mps"):
        pts = sorted((r["seconds"], r["metrics"]["surge_front_error"], r["overrides"]["fluid.spacing"]) for r in ours
                     if r["overrides"]["simulate.use"] == solver and r["metrics"]["surge_front_error"] is not None)
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"ours: {solver}")
    for method, colour in (("dfsph", "black"), ("wcsph", "grey")):
        pts = sorted((r["seconds"], r["surge_front_error"]) for r in peers
                     if r["method"] == method and "surge_front_error" in r and not blew_up(r))
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "s--", color=colour,
                    label=f"SPlisHSPlasH {method.upper()} (stepping, set-up excluded)")
    bad = [f"{r['method'].upper()} l0 = {r['spacing']}" for r in peers if blew_up(r)]
    if bad:
        ax.text(0.02, 0.02, "SPlisHSPlasH left the tank (not plotted): " + ", ".join(bad), transform=ax.transAxes,
                fontsize=6)
    ax.set_xscale("log")
    ax.set_xlabel("simulate wall time (s), 2 cores")
    ax.set_ylabel("surge front RMS error vs Martin & Moyce (T <= 3)")
    ax.set_title("Martin & Moyce dam break: ours and SPlisHSPlasH, same scene and metric")
    ax.grid(True, alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study-json", type=Path, help="a finished accuracy_vs_time study.json (else run the study)")
    ap.add_argument("--ours-md", type=Path, help="our points from a study.md table instead (e.g. the committed "
                    "benchmarks/results/accuracy_vs_time.md: measured on another day, so the times compare loosely)")
    ap.add_argument("--methods", default="dfsph,wcsph")
    ap.add_argument("--replot", action="store_true", help="only redraw the figure from peers_accuracy.json")
    a = ap.parse_args()
    if a.replot:
        res = json.loads((HERE / "results" / "peers_accuracy.json").read_text())
        ours = [{"overrides": {"fluid.spacing": r["spacing"], "simulate.use": r["solver"]}, "seconds": r["seconds"],
                 "metrics": {"surge_front_error": r["surge_front_error"]}} for r in res["ours"]]
        plot(ours, res["splishsplash"], HERE / "results" / "images" / "accuracy_vs_time_peers.png")
        return
    study = yaml.safe_load(STUDY.read_text())
    base = yaml.safe_load((STUDY.parent / study["base"]).read_text())
    metric = next(m for m in study["metrics"] if m["name"] == "surge_front_error")
    load0 = os.getloadavg()[0]
    if a.ours_md:
        ours = read_study_md(a.ours_md)
    elif a.study_json:
        ours = json.loads(a.study_json.read_text())["results"]
    else:
        from pipeline.study import run_study
        _, out = run_study(STUDY)
        ours = json.loads((out / "study.json").read_text())["results"]
    peers = []
    for method in a.methods.split(","):
        for spacing in study["sweep"]["fluid.spacing"]:
            p = peer_point(method, spacing, base, metric)
            peers.append(p)
            print(json.dumps({k: p.get(k) for k in ("method", "spacing", "particles", "surge_front_error", "seconds",
                                                   "setup_s", "density_error_mean", "skipped")}),
                  flush=True)
    res = {"command": " ".join(sys.argv), "load_average_1min_start": load0, "load_average_1min_end": os.getloadavg()[0],
           "ours": [{"solver": r["overrides"]["simulate.use"], "spacing": r["overrides"]["fluid.spacing"],
                     "seconds": r["seconds"], **r["metrics"]} for r in ours],
           "splishsplash": peers}
    (HERE / "results" / "peers_accuracy.json").write_text(json.dumps(res, indent=1) + "\n")
    plot(ours, peers, HERE / "results" / "images" / "accuracy_vs_time_peers.png")


if __name__ == "__main__":
    main()
