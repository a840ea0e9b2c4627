"""Where a cold `make demo` spends its time: per stage, numba compilation against the rest.

Runs the demo's configs in this process, one after another, with an empty numba cache (NUMBA_CACHE_DIR
pointed at a new folder, as in a fresh clone) and a fresh pipeline cache, and records every numba
compilation (numba's "numba:compile" event: only real compilations, not loads from the disk cache)
with its self time (nested compilations of called functions subtracted), the stage it happened in and
its signature. Prints per stage wall seconds and compile seconds, and per kernel the number of
signatures compiled. ``--warm`` runs again with the same (now filled) numba cache for the warm figure.

    python benchmarks/bench_demo_compile.py [configs ...] [--json out.json] [--numba-cache DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEMO = [ROOT / "configs/dam_break_dfsph.yaml", ROOT / "configs/pour.yaml"]


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("configs", nargs="*", type=Path, default=DEMO)
    ap.add_argument("--numba-cache", type=Path, help="numba cache folder (default: a new empty one)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--set", action="append", default=[], help="config override PATH=VALUE (all configs)")
    args = ap.parse_args()
    nb_cache = args.numba_cache or Path(tempfile.mkdtemp(prefix="demo-numba-cache-"))
    os.environ["NUMBA_CACHE_DIR"] = str(nb_cache)  # before numba is imported

    from numba.core import event

    from pipeline import runner

    stage = ["(import)"]
    compiles: list[dict] = []
    stack: list[list] = []

    class Compiles(event.Listener):
        def on_start(self, ev):
            stack.append([time.perf_counter(), 0.0])

        def on_end(self, ev):
            t0, nested = stack.pop()
            total = time.perf_counter() - t0
            if stack:
                stack[-1][1] += total
            disp = ev.data["dispatcher"]
            name = f"{disp.py_func.__module__}.{disp.py_func.__qualname__}"
            compiles.append({"kernel": name, "stage": stage[0], "self": total - nested, "total": total,
                             "sig": str(ev.data["args"])})

    def events(e: dict) -> None:
        if "stage" in e:
            stage[0] = f"{scene}:{e['stage']}"
            stage_start[stage[0]] = time.perf_counter()

    event.register("numba:compile", Compiles())
    work = Path(tempfile.mkdtemp(prefix="demo-profile-"))
    print(f"caches and outputs in {work}, numba cache {nb_cache}", flush=True)
    result = {"numba_cache": str(nb_cache), "load": os.getloadavg(), "scenes": []}
    for cfg in args.configs:
        scene = cfg.stem
        stage_start: dict[str, float] = {}
        t0 = time.perf_counter()
        rep = runner.run(cfg, overrides=tuple(args.set), cache_dir=work / "cache", out_dir=work / scene, events=events)
        wall = time.perf_counter() - t0
        stages = []
        for s in rep.stages:
            key = f"{scene}:{s.kind}"
            comp = sum(c["self"] for c in compiles if c["stage"] == key)
            stages.append({"stage": s.kind, "seconds": round(s.seconds, 2), "compile": round(comp, 2),
                           "status": s.status})
        result["scenes"].append({"config": str(cfg), "seconds": round(wall, 1), "stages": stages})
        print(f"{cfg}: {wall:.1f} s")
        for s in stages:
            print(f"  {s['stage']:16s} {s['seconds']:7.1f} s  compile {s['compile']:6.1f} s  ({s['status']})")
    per_kernel: dict[str, list] = defaultdict(list)
    for c in compiles:
        per_kernel[c["kernel"]].append(c)
    rows = sorted(per_kernel.items(), key=lambda kv: -sum(c["self"] for c in kv[1]))
    print(f"\ncompile self time {sum(c['self'] for c in compiles):.1f} s in {len(compiles)} compilations "
          f"of {len(per_kernel)} functions (load {os.getloadavg()[0]:.1f})")
    print(f"{'self s':>7} {'n':>3}  function  [stages]")
    for name, cs in rows:
        print(f"{sum(c['self'] for c in cs):7.1f} {len(cs):3d}  {name}  [{', '.join(sorted({c['stage'] for c in cs}))}]")
        if len(cs) > 1:
            for c in cs:
                print(f"{'':14s}{c['self']:6.1f} {c['sig'][:300]}")
    result["kernels"] = [{"kernel": n, "self": round(sum(c["self"] for c in cs), 2), "count": len(cs),
                          "signatures": [c["sig"] for c in cs], "stages": sorted({c["stage"] for c in cs})}
                         for n, cs in rows]
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    sys.exit(main())
