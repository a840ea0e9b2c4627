"""`make bench`: every benchmark in turn (each prints its table and writes benchmarks/results/*.json).
Timings are measured here, never asserted in tests: this machine is shared and noisy."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).parent
BENCHES = ["bench_sdf.py", "bench_sph.py", "bench_dfsph.py", "bench_mps.py", "bench_hydrostatic.py", "bench_effects.py", "bench_walls.py",
           "bench_surface.py", "bench_render.py", "compare_sph_mps.py", "dragon_snap_figure.py"]


def main() -> int:
    failed = []
    for name in BENCHES:
        script = HERE / name
        if not script.exists():
            print(f"-- {name}: not present, skipped")
            continue
        print(f"== {name}", flush=True)
        if subprocess.call([sys.executable, str(script)]) != 0:
            failed.append(name)
    if failed:
        print("failed:", ", ".join(failed))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
