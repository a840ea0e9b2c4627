"""Inflow and sinks (issue 18): the cost of an emission and of the sinks at 20k particles, and a tank with a
tap and a floor drain run to its steady level (longer than the CI test, which uses an overflow drain).

    PYTHONPATH=. .venv/bin/python benchmarks/bench_inflow.py [--part cost,drain] [--solver sph] [--seconds 6]

cost: a 20k-particle block of water at rest (l0 = 1 cm, SPH, one thread) with a jet (r = 3 l0, 1 m/s) above it:
the time of one emission (a layer of 29 particles appended: the overlap check, the arrays grown by one copy,
the per-particle buffers rebuilt), of the step after it (which rebuilds the neighbour list the append
invalidated) against a step without emission, and of the sinks' per-step check with nothing and with 20
particles in a sink. drain: a 16 x 16 cm tank (l0 = 2 cm) filled 6 cm deep, a tap (r = 3 cm, 0.5 m/s:
1.41 l/s) and a 4 x 4 cm drain at the floor; every 0.25 s the particles in the tank, the inflow and the
drained volume over the interval.
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.dfsph import DFSPHParams, DFSPHSolver
from stages.simulate.emitters import lattice
from stages.simulate.inflow import Inflow, Sink
from stages.simulate.mps import MPSParams, MPSSolver
from stages.simulate.sph import SPHParams, SPHSolver

G = 9.81


def make(solver: str, x, sdf, l0: float, v_ref: float):
    common = dict(spacing=l0, rho0=1000.0, gravity=(0, 0, -G), mu=0.001)
    ids = np.arange(len(x), dtype=np.int32)
    v = np.zeros_like(x)
    if solver == "sph":
        return SPHSolver(x, v, ids, sdf, params=SPHParams(threads=1), v_ref=v_ref, **common)
    if solver == "mps":
        return MPSSolver(x, v, ids, sdf, params=MPSParams(threads=1), v_ref=v_ref, **common)
    return DFSPHSolver(x, v, ids, sdf, params=DFSPHParams(threads=1), **common)


def cost() -> None:
    import numba as nb
    nb.set_num_threads(1)
    l0 = 0.01
    lo, hi = np.zeros(3), np.array([0.4, 0.25, 0.45])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    x = lattice([0, 0, 0], [0.4, 0.25, 0.2], l0)
    s = make("sph", x, sdf, l0, math.sqrt(1.0 + 2 * G * 0.4))
    jet = Inflow(center=[0.2, 0.125, 0.4], direction=[0, 0, -1], radius=0.03, speed=1.0, start=0.0,
                 end=math.inf, l0=l0)
    s.attach_flows([jet], [Sink(lo=np.array([0.0, 0.0, 0.0]), hi=np.array([0.02, 0.02, 0.011]))])
    s.step(s.t + 1.0)  # compile
    plain, emit, after, flag = [], [], [], [False]
    emit_inflow, step = s.emit_inflow, s.step

    def timed_emit() -> int:
        t0 = time.perf_counter(); n = emit_inflow(); dt = time.perf_counter() - t0
        if n:
            assert n == len(jet.disc)
            emit.append(dt)
            flag[0] = True
        return n

    def timed_step(t_end: float) -> float:
        t0 = time.perf_counter(); dt = step(t_end)
        (after if flag[0] else plain).append(time.perf_counter() - t0)
        flag[0] = False
        return dt

    s.emit_inflow, s.step = timed_emit, timed_step
    s.advance_to(0.1)  # ten layers
    del s.emit_inflow, s.step
    print(f"cost at {len(s.x)} particles (sph, 1 thread): step {1e3 * np.median(plain):.2f} ms, emission of a "
          f"{len(jet.disc)}-particle layer {1e3 * np.median(emit):.2f} ms, the step after it "
          f"{1e3 * np.median(after):.2f} ms (neighbour list rebuilt); {len(emit)} emissions in {s.steps} steps")
    print(f"  layer period {1e3 * jet.period:.2f} ms = {len(plain + after) / len(emit):.0f} steps a layer: "
          f"{1e2 * (np.median(emit) + np.median(after) - np.median(plain)) / np.median(plain) / (len(plain + after) / len(emit)):.2f} "
          "% added to the stepping")
    s.sinks = (Sink(lo=np.array([0.5, 0.5, 0.5]), hi=np.array([0.6, 0.6, 0.6])),)  # empty: the check only
    t0 = time.perf_counter()
    for _ in range(100):
        s.drain_sinks()
    check = (time.perf_counter() - t0) / 100
    s.sinks = (Sink(lo=np.array([0.0, 0.0, 0.0]), hi=np.array([0.05, 0.04, 0.011])),)  # the floor row: 20 inside
    t0 = time.perf_counter(); gone = s.drain_sinks(); drain = time.perf_counter() - t0
    t0 = time.perf_counter(); s.step(s.t + 1.0); step_after = time.perf_counter() - t0
    print(f"  sinks: check {1e3 * check:.3f} ms a step; removing {gone} particles {1e3 * drain:.2f} ms, the step "
          f"after it {1e3 * step_after:.2f} ms")


def drain(solver: str, seconds: float) -> None:
    l0 = 0.02
    W, H = 0.16, 0.4
    lo, hi = np.zeros(3), np.array([W, W, H])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0 / 2)
    x = lattice([0, 0, 0], [W, W, 0.06], l0)  # near the steady level (about 6 cm: 10 cm drains to it in ~4 s)
    jet = Inflow(center=[0.05, 0.05, 0.34], direction=[0, 0, -1], radius=0.03, speed=0.5, start=0.0,
                 end=math.inf, l0=l0)
    s = make(solver, x, sdf, l0, math.sqrt(0.25 + 2 * G * H))
    s.attach_flows([jet], [Sink(lo=np.array([W - 0.04, W - 0.04, -0.01]), hi=np.array([W + 0.01, W + 0.01, 0.02]))])
    q = jet.volume_rate / l0 ** 3
    print(f"drain ({solver}): tap {1e3 * jet.volume_rate:.3f} l/s = {q:.1f} particles/s; start {len(s.x)} particles")
    print("   t [s]  in tank  level [cm]  inflow [l/s]  drained [l/s]")
    dt_out, t0 = 0.25, time.perf_counter()
    last = (0, 0)
    for k in range(1, int(round(seconds / dt_out)) + 1):
        s.advance_to(k * dt_out)
        inflow, sunk = s.inflow_particles - last[0], s.sunk - last[1]
        last = (s.inflow_particles, s.sunk)
        below_jet = s.x[np.hypot(s.x[:, 0] - 0.05, s.x[:, 1] - 0.05) > 0.05]
        level = float(np.percentile(below_jet[:, 2], 98)) + 0.5 * l0 if len(below_jet) else 0.0
        print(f"  {s.t:6.2f}  {len(s.x):7d}  {100 * level:10.1f}  {inflow * l0 ** 3 / dt_out * 1e3:12.3f}  "
              f"{sunk * l0 ** 3 / dt_out * 1e3:13.3f}")
        if k * dt_out == seconds - 2.0:
            mark = (s.inflow_particles, s.sunk, len(s.x))
    inflow, sunk, count = s.inflow_particles - mark[0], s.sunk - mark[1], len(s.x) - mark[2]
    print(f"  the last 2 s: inflow {inflow} particles, drained {sunk} ({100 * (sunk / inflow - 1):+.1f} %), "
          f"in the tank {count:+d}")
    print(f"  ({time.perf_counter() - t0:.0f} s wall, {s.steps} steps)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", default="cost,drain")
    ap.add_argument("--solver", default="sph", choices=["sph", "dfsph", "mps"])
    ap.add_argument("--seconds", type=float, default=6.0)
    a = ap.parse_args()
    if "cost" in a.part:
        cost()
    if "drain" in a.part:
        drain(a.solver, a.seconds)


if __name__ == "__main__":
    main()
