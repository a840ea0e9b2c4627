"""`make bench`: every benchmark in turn (each prints its table and writes benchmarks/results/*.json), then
one summary table of issue 20's comparisons with the peers (ours, the peer, the ratio, the goal, met?).
Timings are measured here, never asserted in tests: this machine is shared and noisy."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).parent
RESULTS = HERE / "results"
BENCHES = ["bench_sdf.py", "bench_emission.py", "bench_sph.py", "bench_sph_kernels.py", "bench_dfsph.py", "bench_mps.py", "bench_hydrostatic.py", "bench_effects.py", "bench_walls.py", "bench_wall_maps.py",
           "bench_wall_offset.py",
           "bench_surface.py", "bench_render.py", "compare_sph_mps.py", "dragon_snap_figure.py",
           "bench_peers.py", "bench_shot.py", "peers_accuracy_plot.py", "convergence_plot.py --run",
           "convergence_plot.py --study sloshing --run"]


def _load(name: str) -> dict | None:
    f = RESULTS / name
    try:
        return json.loads(f.read_text()) if f.is_file() else None
    except json.JSONDecodeError:
        return None


def summary_rows() -> list[tuple[str, str, str, str, str, str]]:
    """(what, ours, peer, ratio, goal, met) from the results JSONs that exist."""
    rows = []
    for name, label in (("peers.json", "20k"), ("peers_100k.json", "100k")):
        r = _load(name)
        if not r or "goal" not in r:
            continue
        g = r["goal"]
        best = r["equal_accuracy"][g["best_solver"]]
        rows.append((f"dam break {label}: wall s / simulated s at equal density error ({g['best_solver']} vs "
                     f"SPlisHSPlasH DFSPH)", f"{best['ours_wall_s_per_sim_s']:.2f}",
                     f"{best['peer_dfsph_at_equal_error']:.2f}",
                     f"{g['best_ratio']:.2f}" + (f" (CPU {g['best_cpu_ratio']:.2f})" if "best_cpu_ratio" in g else ""), "<= 0.5",
                     "yes" if g["ratio_met"] else "no"))
        if "step_ratio_dfsph" in g:
            peer = next(v for k, v in r["splishsplash"].items() if k.startswith("DFSPH") and "ms_per_step" in v
                        and abs(v["job"]["max_error"] - 0.1) < 1e-9)
            rows.append((f"dam break {label}: DFSPH ms per step, same tolerance", f"{r['ours']['dfsph']['ms_per_step']:.1f}",
                         f"{peer['ms_per_step']:.1f}", f"{g['step_ratio_dfsph']:.2f}"
                         + (f" (CPU {g['step_cpu_ratio_dfsph']:.2f})" if "step_cpu_ratio_dfsph" in g else ""), "<= 1", "yes" if g["step_met"] else "no"))
    s = _load("shot.json")
    if s and "goal" in s:
        g = s["goal"]
        rows.append((f"whole shot, demo dam break ({s['best_solver']}), s", f"{g['ours_s']:.1f}", "-", "-", "<= 30 s",
                     "yes" if g["time_met"] else "no"))
        if "peer_over_ours" in g:
            rows.append(("whole shot vs SPlisHSPlasH + splashsurf + our renderer, s", f"{g['ours_s']:.1f}",
                         f"{s['peer']['total_s']:.1f}", f"{g['peer_over_ours']:.2f}x ahead"
                         + (f" (CPU {g['peer_over_ours_cpu']:.2f}x)" if "peer_over_ours_cpu" in g else ""), ">= 2x ahead",
                         "yes" if g["ratio_met"] else "no"))
    p = _load("peers_accuracy.json")
    if p:
        fine = min(r["spacing"] for r in p["ours"])
        for method, solver in (("dfsph", "dfsph"), ("wcsph", "sph")):
            o = next((r for r in p["ours"] if r["solver"] == solver and r["spacing"] == fine), None)
            q = next((r for r in p["splishsplash"] if r["method"] == method and r["spacing"] == fine
                      and "surge_front_error" in r), None)
            if o and q and q["surge_front_error"] > 1.0:
                rows.append((f"Martin & Moyce l0 = {fine}: {solver} vs SPlisHSPlasH {method.upper()}, s (surge error)",
                             f"{o['seconds']:.1f} ({o['surge_front_error']:.3f})", "left the tank", "-", "-", "-"))
            elif o and q:
                rows.append((f"Martin & Moyce l0 = {fine}: {solver} vs SPlisHSPlasH {method.upper()}, s (surge error; "
                             f"times from separate runs)", f"{o['seconds']:.1f} ({o['surge_front_error']:.3f})",
                             f"{q['seconds']:.1f} ({q['surge_front_error']:.3f})", f"{o['seconds'] / q['seconds']:.2f}",
                             "-", "-"))
    for study, metrics in (("convergence", (("distance_to_finest", "distance to finest"),
                                            ("front_speed_error", "front speed vs Ritter"))),
                           ("sloshing", (("frequency_error", "frequency vs linear theory"),
                                         ("damping_error", "damping vs water's")))):
        c = _load(f"{study}.json")
        for solver, row in (c or {}).items():
            for m, what in metrics:
                if f"{m}_order" in row:
                    x = row[f"{m}_time_per_halving"]
                    per_halving = f"x{x:.1f}" if x <= 100 else "> x100" if math.isfinite(x) else "none"
                    rows.append((f"{study} {solver}: {what}: observed order, time per halving of the error",
                                 f"{row[f'{m}_order']:.2f}, {per_halving}", "-", "-", "error falls with cost",
                                 "yes" if x <= 100 else "no"))
    return rows


def print_summary() -> None:
    rows = summary_rows()
    if not rows:
        print("summary: no peer results yet")
        return
    head = ("comparison (issue 20)", "ours", "peer", "ratio", "goal", "met")
    widths = [max(len(r[i]) for r in rows + [head]) for i in range(6)]
    for r in [head, tuple("-" * w for w in widths)] + rows:
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))


def main() -> int:
    failed = []
    for entry in BENCHES:
        name, *args = entry.split()
        script = HERE / name
        if not script.exists():
            print(f"-- {name}: not present, skipped")
            continue
        print(f"== {entry}", flush=True)
        if subprocess.call([sys.executable, str(script), *args]) != 0:
            failed.append(name)
    if failed:
        print("failed:", ", ".join(failed))
    print_summary()
    return 1 if failed else 0


if __name__ == "__main__":
    if sys.argv[1:] == ["--summary"]:
        print_summary()
        sys.exit(0)
    sys.exit(main())
