"""Benchmark of ``pipeline study --executor dask``: a smaller accuracy-vs-time study (the Martin & Moyce
dam break, configs/studies/accuracy_vs_time.yaml, at its two coarsest spacings, all three solvers) on a
LocalCluster of 1 and of 2 worker processes, each from an empty cache.

Run: ``python benchmarks/bench_dask_study.py [--spacings 0.03125 0.025] [--workers 1 2]``.
Prints, and writes to benchmarks/results/dask_study.json: the study's wall time per worker count and the
speed-up; the stage runs the cache saved (every variant needs mesh_import, sdf_bake and simulate; shared
upstream keys run once); each variant's cost column (simulate wall without warm-up) and CPU seconds for
each worker count, and the load average before and after (the machine is shared).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
STUDY = ROOT / "configs" / "studies" / "accuracy_vs_time.yaml"


def small_study(folder: Path, spacings: list[float]) -> Path:
    study = yaml.safe_load(STUDY.read_text())
    study["name"] = "accuracy_vs_time_small"
    study["base"] = str((STUDY.parent / study["base"]).resolve())
    study["sweep"]["fluid.spacing"] = spacings
    for m in study["metrics"]:
        if "reference" in m.get("args", {}):
            m["args"]["reference"] = str((STUDY.parent / m["args"]["reference"]).resolve())
    path = folder / "study.yaml"
    path.write_text(yaml.safe_dump(study, sort_keys=False))
    return path


def stage_runs(cache: Path) -> dict[str, int]:
    """Whole-run cache entries per stage kind: each is one stage run."""
    return {kind: len(list((cache / kind).glob("*/*/manifest.json")))
            for kind in ("mesh_import", "sdf_bake", "simulate") if (cache / kind).is_dir()}


def warm_up(out: Path) -> float:
    """The simulate stage's warm-up (JIT compile) left out of its cost: its wall time minus its cost."""
    stage = next(s for s in json.loads((out / "run.json").read_text())["stages"] if s["kind"] == "simulate")
    return stage["seconds"] - stage["cost_seconds"]


def main() -> None:
    from pipeline.study import run_study, variants, load_study

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spacings", type=float, nargs="+", default=[0.03125, 0.025])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "dask_study.json")
    args = ap.parse_args()
    os.environ.setdefault("NUMBA_THREADING_LAYER", "omp")
    work = Path(tempfile.mkdtemp(prefix="bench_dask_study."))
    path = small_study(work, args.spacings)
    n_variants = len(variants(load_study(path)))
    result = {"machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                          "load_before": os.getloadavg()},
              "study": {"spacings": args.spacings, "solvers": ["sph", "dfsph", "mps"], "variants": n_variants},
              "runs": {}}
    for w in args.workers:
        cache, out = work / f"cache{w}", work / f"out{w}"
        t0 = time.perf_counter()
        results, _ = run_study(path, cache_dir=cache, out_dir=out, executor="dask", workers=w)
        wall = time.perf_counter() - t0
        runs = stage_runs(cache)
        result["runs"][str(w)] = {
            "wall_seconds": wall, "stage_runs": runs,
            "variants": [{**{k.split(".")[-1]: v for k, v in r.overrides.items()},
                          "simulate_seconds": r.seconds, "simulate_cpu_seconds": r.cpu_seconds,
                          "simulate_warmup_seconds": warm_up(Path(r.out)), **r.metrics}
                         for r in results]}
        print(f"{w} worker process(es): {wall:.1f} s, stage runs {runs}")
        for r in results:
            print(f"   {r.overrides}: simulate {r.seconds:.2f} s wall (no warm-up), {r.cpu_seconds:.2f} s CPU, "
                  f"warm-up {warm_up(Path(r.out)):.2f} s")
    naive = 3 * n_variants  # mesh_import, sdf_bake and simulate for every variant
    first = result["runs"][str(args.workers[0])]
    done = sum(first["stage_runs"].values())
    result["stage_runs"] = {"without_sharing": naive, "with_sharing": done, "saved": naive - done}
    if len(args.workers) > 1:
        a, b = min(args.workers), max(args.workers)
        result["speedup"] = result["runs"][str(a)]["wall_seconds"] / result["runs"][str(b)]["wall_seconds"]
        print(f"speed-up {a} -> {b} worker processes: {result['speedup']:.2f}x")
    print(f"stage runs: {done} instead of {naive} ({naive - done} saved by shared upstream keys)")
    result["machine"]["load_after"] = os.getloadavg()
    print(f"load average before {result['machine']['load_before']}, after {result['machine']['load_after']}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
