"""Which motions a solver's step amplifies at rest (issue 17): one step linearised about a resting tank.

A small tank (0.1 x 0.075 m, water 0.1 m deep at 1.25 cm: 384 particles; bench_rest's walls, start and
water's viscosity) is first held still (every velocity zeroed after each step, for --settle seconds), then the step
is differentiated by central differences, column by column, in the state (positions, velocities and the
pressure a solver carries from step to step, matched by particle id) at the step the solver takes at rest.
The eigenvalues of that Jacobian are the per-step growth factors of small disturbances: a real factor above 1 is a
motion that grows without oscillating (rate ln|lambda| / dt), one at arg pi a step-to-step flip. Printed per
solver: the largest rates, in 1/s and in units of sqrt(g / l0) (a particle-scale gravitational rate), the
number of modes above half that, and where the fastest mode lives (shares of its motion in the top and bottom
layers and within 1.5 l0 of a side wall, beside those layers' shares of the particles) and its vertical share.
Also how far the step's forces are from conservative: |K - K^T| / |K + K^T| of K = d v_new / d x (a force that is
minus an energy's gradient has a symmetric K), over all particles and over the interior.

The derivative needs a smooth step: MPS's CG is solved to 1e-12 (its default 1e-6 gives the same rates),
DFSPH's two Jacobi solves run a fixed 50 iterations (their default stops at a tolerance, a switch a finite
difference cannot follow); the wall clamps, free-surface flags and p_min choices stay as the base state has them
for disturbances of 1e-7 l0.

    .venv/bin/python benchmarks/bench_rest_modes.py [--solvers sph,dfsph,mps] [--gravity-scale 0.25]

Writes benchmarks/results/rest_modes.json (about a minute on 2 threads)."""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_rest as B  # noqa: E402  (the tank, its start and the solvers' constructors)

SMOOTH = {"mps": {"cg_tolerance": 1e-12},
          "dfsph": {"max_density_error": 1e-9, "max_divergence_error": 1e-9, "max_iterations": 50}}
PRESSURES = ("pr", "kappa", "kappa_v")  # the carried arrays that are pressures (MPS: Pa; DFSPH: p / rho)


class Linearised:
    """A solver's step as a map of the scaled state z = (x / l0, v / sqrt(g l0), carried pressures / (g l0 [rho]))."""

    def __init__(self, solver, name: str, g: float):
        self.s, self.g = solver, g
        self.l0 = solver.l0
        self.carried = [c for c in getattr(solver, "carried", ()) if c in PRESSURES]
        self.p_scale = g * self.l0 * (B.RHO0 if name == "mps" else 1.0)
        self.width = 6 + len(self.carried)

    def get(self) -> np.ndarray:
        s = self.s
        o = np.argsort(s.id)
        parts = [s.x[o] / self.l0, s.v[o] / math.sqrt(self.g * self.l0)]
        parts += [getattr(s, c)[o][:, None] / self.p_scale for c in self.carried]
        return np.concatenate(parts, axis=1).ravel()

    def put(self, z: np.ndarray) -> None:
        s = self.s
        z = z.reshape(len(s.x), self.width)
        o = np.argsort(s.id)
        s.x[o] = z[:, :3] * self.l0
        s.v[o] = z[:, 3:6] * math.sqrt(self.g * self.l0)
        for k, c in enumerate(self.carried):
            getattr(s, c)[o] = z[:, 6 + k] * self.p_scale
        if hasattr(s, "_fresh"):
            s._fresh = False  # DFSPH: density and neighbour lists from these positions

    def step(self, z: np.ndarray, dt: float) -> np.ndarray:
        s = self.s
        self.put(z)
        t, steps = s.t, s.steps
        s.step(s.t + dt)
        out = self.get()
        s.t, s.steps = t, steps
        return out


def analyse(name: str, settle_seconds: float, eps: float, gravity_scale: float, top: int) -> dict:
    s = B.make(name, SMOOTH.get(name, {}))
    s.gravity[:] *= gravity_scale
    g = B.G
    dt = s.step(math.inf)  # the step the solver takes at rest (its cap: no velocity sets it)
    settle = int(round(settle_seconds / dt))
    for _ in range(settle):
        s.step(s.t + dt)
        s.v[:] = 0.0
    lin = Linearised(s, name, g)
    z0 = lin.get()
    z1 = lin.step(z0, dt)
    n = len(s.x)
    residual = float(np.abs(z1.reshape(n, lin.width)[:, 3:6]).max() * math.sqrt(g * lin.l0) / dt / g)
    t0 = time.perf_counter()
    jac = np.empty((len(z0), len(z0)))
    for k in range(len(z0)):
        e = np.zeros(len(z0))
        e[k] = eps
        jac[:, k] = (lin.step(z0 + e, dt) - lin.step(z0 - e, dt)) / (2 * eps)
    seconds = time.perf_counter() - t0
    lam, vec = np.linalg.eig(jac)
    order = np.argsort(-np.abs(lam))
    unit = math.sqrt(g / lin.l0)
    x = z0.reshape(n, lin.width)[:, :3]
    z = x[:, 2]
    where = {"top_2_layers": z > z.max() - 1.5, "bottom_2_layers": z < z.min() + 1.5,
             "side_1.5_l0": B.side_distance(x * lin.l0) < 1.5 * lin.l0}
    modes = []
    for i in order[:top]:
        m = vec[:, i].reshape(n, lin.width)
        motion = np.abs(m[:, :6]).sum(1)
        motion /= motion.sum()
        dx2 = (np.abs(m[:, :3]) ** 2).sum(0)
        modes.append({"growth": float(abs(lam[i])), "rate": math.log(abs(lam[i])) / dt,
                      "rate_sqrt_g_l0": math.log(abs(lam[i])) / dt / unit, "arg": float(np.angle(lam[i])),
                      "vertical_share": float(dx2[2] / dx2.sum()),
                      "share": {k: float(motion[sel].sum()) for k, sel in where.items()},
                      "largest_particle_share": float(motion.max())})
    fast = int(np.sum(np.log(np.maximum(np.abs(lam), 1e-300)) / dt > 0.5 * unit))
    # how far the step's forces are from conservative: a force that is minus an energy's gradient has a symmetric
    # stiffness, so d v_new / d x (equal masses) is symmetric; measured over all particles and the interior
    # (1.5 l0 or more from the floor and the side walls, below the top two layers)
    interior = (z > z.min() + 1.5) & (z < z.max() - 2.5) & ~where["side_1.5_l0"]
    asymmetry = {}
    for key, sel in (("all", np.ones(n, bool)), ("interior", interior)):
        rows = (np.flatnonzero(sel)[:, None] * lin.width + np.arange(3)).ravel()
        k = jac[np.ix_(rows + 3, rows)]
        asymmetry[key] = float(np.linalg.norm(k - k.T) / np.linalg.norm(k + k.T))
    return {"solver": name, "particles": n, "dt": dt, "gravity_scale": gravity_scale, "settle_steps": settle,
            "settled_max_accel_g": residual, "jacobian_seconds": seconds, "modes_above_half_sqrt_g_l0": fast,
            "particle_share": {k: float(sel.mean()) for k, sel in where.items()},
            "interior_particles": int(interior.sum()),
            "stiffness_asymmetry": asymmetry, "modes": modes}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--solvers", default="sph,dfsph,mps")
    ap.add_argument("--settle", type=float, default=0.35, help="seconds of the solver's steps held still "
                    "before the linearisation")
    ap.add_argument("--eps", type=float, default=1e-7, help="the finite difference, in the scaled state")
    ap.add_argument("--gravity-scale", type=float, default=1.0, help="gravity times this, once the start is "
                    "made (a rate that is gravity's halves at 0.25)")
    ap.add_argument("--top", type=int, default=5, help="modes printed per solver")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "rest_modes.json"))
    a = ap.parse_args()
    import numba as nb
    nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
    B.SIZE, B.DEPTH, B.TANK_H = (0.1, 0.075), 0.1, 0.15
    results = []
    for name in a.solvers.split(","):
        r = analyse(name, a.settle, a.eps, a.gravity_scale, a.top)
        results.append(r)
        sh = r["particle_share"]
        print(f"{name}: {r['particles']} particles, dt {1e3 * r['dt']:.3f} ms, held still {r['settle_steps']} steps "
              f"(largest acceleration left {r['settled_max_accel_g']:.3f} g), {r['modes_above_half_sqrt_g_l0']} modes "
              f"faster than 0.5 sqrt(g / l0); particles' shares: top {sh['top_2_layers']:.2f}, bottom "
              f"{sh['bottom_2_layers']:.2f}, side {sh['side_1.5_l0']:.2f}; stiffness |antisymmetric| / |symmetric| "
              f"{r['stiffness_asymmetry']['all']:.3f}, in the interior ({r['interior_particles']} particles) "
              f"{r['stiffness_asymmetry']['interior']:.3f} (0 for conservative forces)", flush=True)
        for m in r["modes"]:
            kind = "flip" if abs(abs(m["arg"]) - math.pi) < 0.1 else ("grows" if abs(m["arg"]) < 0.1 else "rings")
            w = m["share"]
            print(f"  rate {m['rate']:8.2f}/s = {m['rate_sqrt_g_l0']:5.2f} sqrt(g/l0) {kind:5}  vertical "
                  f"{m['vertical_share']:.2f}  top {w['top_2_layers']:.2f} bottom {w['bottom_2_layers']:.2f} side "
                  f"{w['side_1.5_l0']:.2f}  one particle at most {m['largest_particle_share']:.2f}", flush=True)
    Path(a.out).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
