"""A convergence study's figure (issue 20): error against simulate time for each solver, with each solver's
observed order of convergence and what each halving of the error costs.

    python benchmarks/convergence_plot.py [--study convergence|sloshing] [--study-json STUDY.json] [--run]

``--run`` runs `pipeline study configs/studies/<study>.yaml` first (through the cache). Writes
benchmarks/results/<study>.json, <study>.md and images/<study>.png."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))

from stages.simulate.validation import cost_per_halving, observed_order  # noqa: E402

# per study: its metrics (name -> axis label) and the figure's title
STUDIES = {
    "convergence": ({"front_speed_error": "|front speed / 2 sqrt(gH) - 1|, 0.1-0.2 s",
                     "distance_to_finest": "surge front RMS distance to the finest run / a"},
                    "Martin & Moyce dam break at a/8, a/12, a/16: error against cost"),
    "sloshing": ({"frequency_error": "|f / f1 - 1|, first sloshing mode vs linear theory",
                  "damping_error": "|damping ratio - water's (0.006)|, first mode"},
                 "Free sloshing, 10 / 15 / 20 particles of depth: error against cost"),
}
def summarise(results: list[dict], metrics: dict) -> dict:
    out = {}
    for solver in sorted({r["overrides"]["simulate.use"] for r in results}):
        rs = sorted((r for r in results if r["overrides"]["simulate.use"] == solver),
                    key=lambda r: -r["overrides"]["fluid.spacing"])
        h = [r["overrides"]["fluid.spacing"] for r in rs]
        t = [r["seconds"] for r in rs]
        row = {"spacing": h, "seconds": t}
        for m in metrics:
            e = [r["metrics"][m] for r in rs]
            row[m] = e
            pts = [(hh, tt, ee) for hh, tt, ee in zip(h, t, e) if ee is not None and ee > 0]
            if len(pts) >= 2:
                row[f"{m}_order"] = observed_order([p[0] for p in pts], [p[2] for p in pts])
                row[f"{m}_time_per_halving"] = cost_per_halving([p[1] for p in pts], [p[2] for p in pts])
        out[solver] = row
    return out


def halving(x: float | None) -> str:
    """A time factor per halving of the error: above 100x the error barely falls over these runs; infinite, it
    is flat or rising."""
    if x is None:
        return "-"
    if x <= 100:
        return f"x{x:.1f}"
    return "> x100" if math.isfinite(x) else "none (flat or rising)"


def plot(summary: dict, path: Path, metrics: dict, title: str) -> None:
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=120)
    for ax, (m, label) in zip(axes, metrics.items()):
        for solver, row in summary.items():
            pts = [(t, e) for t, e in zip(row["seconds"], row[m]) if e is not None and e > 0]
            if not pts:
                continue
            order, per_halving = row.get(f"{m}_order"), row.get(f"{m}_time_per_halving")
            tag = f"{solver}: order {order:.2f}, time per halving {halving(per_halving)}" if order is not None else solver
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", label=tag)
        ax.set_xlabel("simulate wall time (s), 2 cores")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def markdown(summary: dict, metrics: dict) -> str:
    names = list(metrics)
    lines = ["| solver | spacing | simulate s | " + " | ".join(names) + " |", "|---" * (3 + len(names)) + "|"]
    for solver, row in summary.items():
        for k, (h, t) in enumerate(zip(row["spacing"], row["seconds"])):
            lines.append(f"| {solver} | {h:.4g} | {t:.1f} | " + " | ".join(f"{row[m][k]:.4f}" for m in names) + " |")
    lines += ["", "| solver | " + " | ".join(f"observed order ({m}) | time per halving ({m})" for m in names) + " |",
              "|---" * (1 + 2 * len(names)) + "|"]
    for solver, row in summary.items():
        cells = [row.get(f"{m}_{k}") for m in names for k in ("order", "time_per_halving")]
        lines.append(f"| {solver} | " + " | ".join("-" if c is None else (f"{c:.2f}" if i % 2 == 0 else halving(c))
                                                   for i, c in enumerate(cells)) + " |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--study", choices=sorted(STUDIES), default="convergence")
    ap.add_argument("--study-json", type=Path, help="default: configs/studies/out/<study>/study.json")
    ap.add_argument("--run", action="store_true", help="run the study first")
    a = ap.parse_args()
    study = ROOT / "configs" / "studies" / f"{a.study}.yaml"
    metrics, title = STUDIES[a.study]
    if a.run:
        from pipeline.study import run_study
        _, out = run_study(study)
        a.study_json = out / "study.json"
    a.study_json = a.study_json or study.parent / "out" / a.study / "study.json"
    summary = summarise(json.loads(a.study_json.read_text())["results"], metrics)
    (HERE / "results" / f"{a.study}.json").write_text(json.dumps(summary, indent=1) + "\n")
    md = markdown(summary, metrics)
    (HERE / "results" / f"{a.study}.md").write_text(f"# {a.study} study (configs/studies/{a.study}.yaml)\n\n" + md)
    print(md)
    plot(summary, HERE / "results" / "images" / f"{a.study}.png", metrics, title)


if __name__ == "__main__":
    main()
