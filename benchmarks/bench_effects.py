"""Effects benchmark (issue 8): ms/step on the PEERS.md 20k dam break (1 m cube in a 3 x 2 x 1.2 m tank,
walls on) for each effect set, side by side in one run, plus the hand-written pressure-only kernel
(``reference_forces_pressure``: the kernel sph_kernels had before issue 8, kept in step with its
arithmetic and neighbour list) that the generic kernel with every effect absent must not be slower than.

    python benchmarks/bench_effects.py [--n 20000] [--steps 20] [--rounds 3] [--no-asm]

Variants are timed round-robin (``rounds`` x ``steps`` each, best round kept) so machine noise hits
all alike. Unless --no-asm, also the machine-code size of each effect set's build of sph_kernels.forces
(recompiled uncached, since numba cannot inspect cached code): it grows only with declared effects, the
evidence that absent effects are pruned at compile time. Writes benchmarks/results/effects.json."""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numba as nb
import numpy as np

from pipeline.scene import Effects
from stages.common.sdf import box_interior_sdf, grid_from_function
from stages.simulate.effects import compile_effects
from stages.simulate.emitters import lattice
from stages.simulate.kernels import spiky_grad_coef
from stages.simulate.sph import SPHParams, SPHSolver
from stages.simulate.walls.maps import map_density


@nb.njit(cache=True, parallel=True, fastmath=True)  # built like sph_kernels.forces
def reference_forces_pressure(x, v, p, d, nbr, cnt, inv_rho, h, spiky_coef, mass,
                              wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, gravity, av, acc):
    """Hand-written pressure (eq. 6, 8, Monaghan av) + gravity + the conservative wall pressure
    -(p_i / rho_i^2) grad Z over the solver's neighbour list (the pairs r < h first in each row, cnt of
    them): no other code but the wall density lookup (walls.maps.map_density)."""
    h2 = h * h
    gx0 = gravity[0]
    gy0 = gravity[1]
    gz0 = gravity[2]
    for i in nb.prange(x.shape[0]):
        xi = x[i, 0]
        yi = x[i, 1]
        zi = x[i, 2]
        vxi = v[i, 0]
        vyi = v[i, 1]
        vzi = v[i, 2]
        pi = p[i]
        inv_rhoi = inv_rho[i]
        eps = 0.01 * h2
        ax = 0.0
        ay = 0.0
        az = 0.0
        near_wall = d[i] < h
        for jj in range(cnt[i]):
            j = nbr[i, jj]
            dx = xi - x[j, 0]
            dy = yi - x[j, 1]
            dz = zi - x[j, 2]
            r2 = dx * dx + dy * dy + dz * dz
            if r2 < h2 and r2 > 1e-24:
                r = math.sqrt(r2)
                hr = h - r
                vdx = (vxi - v[j, 0]) * dx + (vyi - v[j, 1]) * dy + (vzi - v[j, 2]) * dz
                inv_rhoj = inv_rho[j]
                den = (r2 + eps) * (inv_rhoi + inv_rhoj)
                f = inv_rhoj * ((pi + p[j]) * den + av * (abs(vdx) - vdx)) * (hr * hr) / (den * r)
                ax += f * dx
                ay += f * dy
                az += f * dz
        c = mass * spiky_coef * inv_rhoi
        ax = ax * c + gx0
        ay = ay * c + gy0
        az = az * c + gz0
        if near_wall:
            e = 0.5 / winv
            ce = 0.5 / e
            zx = ce * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi + e, yi, zi)
                       - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi - e, yi, zi))
            zy = ce * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi + e, zi)
                       - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi - e, zi))
            zz = ce * (map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi + e)
                       - map_density(wmap, wo, winv, fix_rho, inv_dr, sdf, sdf_o, sdf_inv, h, xi, yi, zi - e))
            cw = -pi * inv_rhoi * inv_rhoi
            ax += cw * zx
            ay += cw * zy
            az += cw * zz
        acc[i, 0] = ax
        acc[i, 1] = ay
        acc[i, 2] = az


class ReferenceSolver(SPHSolver):
    """SPHSolver stepping with the hand-written pressure + gravity kernel (no effects)."""

    def forces(self) -> None:
        reference_forces_pressure(self.x, self.v, self.pr, self.d, self.nbr, self.cnt_in, self.inv_rho,
                                  self.h, spiky_grad_coef(self.h) / self.grad_norm, self.mass, self.walls.maps,
                                  self.walls.origin, 1.0 / self.walls.spacing, self.walls.fix_rho, self.inv_dr,
                                  self.sdf.dist, self.sdf.origin, self.sdf_inv,
                                  self.gravity, self.p.artificial_viscosity * self.c * self.h, self.acc)


VARIANTS = {
    "pressure_only_reference": None,
    "pressure_only": {},
    "+viscosity": {"viscosity": {"mu": 0.01}},
    "+surface_tension": {"surface_tension": {"gamma": 0.0728}},
    "+wall_adhesion": {"wall_adhesion": {"beta": 1.0}},
    "+all": {"viscosity": {"mu": 0.01}, "surface_tension": {"gamma": 0.0728}, "wall_adhesion": {"beta": 1.0},
             "wall_friction": {"rate": 5.0}, "wind": {"velocity": [2.0, 0.0, 0.0]},
             "attractor": {"point": [0.0, 0.0, 1.0], "strength": -1.0}},
}


def dam_break(n_target: int, effects: dict | None):
    l0 = 1.0 / round(n_target ** (1 / 3))
    lo, hi = np.array([-1.5, -1.0, 0.0]), np.array([1.5, 1.0, 1.2])
    sdf = grid_from_function(box_interior_sdf(lo, hi), lo, hi, l0)
    x = lattice([-1.5, -1.0, 0.0], [-0.5, 0.0, 1.0], l0)
    params = SPHParams(kernel="poly6_spiky")  # the hand-written reference is the Spiky gradient's kernel
    cls = ReferenceSolver if effects is None else SPHSolver
    consts = compile_effects(Effects(**(effects or {})), meters_per_unit=1.0, rho0=1000.0, l0=l0,
                             h=params.support * l0)
    return cls(x, np.zeros_like(x), np.arange(len(x)), sdf, spacing=l0, rho0=1000.0, params=params,
               gravity=(0, 0, -9.81), v_ref=math.sqrt(2 * 9.81 * 1.0), effects=consts)


def asm_sizes(n: int) -> dict:
    """Bytes of assembly of the generic forces kernel per variant (an uncached build)."""
    from stages.simulate import sph_kernels as K
    global reference_forces_pressure
    cached, uncached = K.forces, nb.njit(parallel=True)(K.forces.py_func)
    cached_ref = reference_forces_pressure
    uncached_ref = nb.njit(parallel=True)(reference_forces_pressure.py_func)
    out = {}
    try:
        K.forces = uncached
        reference_forces_pressure = uncached_ref
        for name, eff in VARIANTS.items():
            fn = uncached_ref if eff is None else uncached
            before = set(fn.signatures)
            dam_break(min(n, 2000), eff).step(10.0)
            sig = (set(fn.signatures) - before).pop()
            out[name] = len(fn.inspect_asm(sig))
    finally:
        K.forces = cached
        reference_forces_pressure = cached_ref
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=20000)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--no-asm", dest="asm", action="store_false")
    a = ap.parse_args()
    solvers = {name: dam_break(a.n, eff) for name, eff in VARIANTS.items()}
    for s in solvers.values():
        for _ in range(3):  # compile and leave the lattice start
            s.step(10.0)
    best = {name: math.inf for name in solvers}
    for _ in range(a.rounds):
        for name, s in solvers.items():
            t0 = time.perf_counter()
            for _ in range(a.steps):
                s.step(10.0)
            best[name] = min(best[name], (time.perf_counter() - t0) / a.steps)
    asm = asm_sizes(a.n) if a.asm else {}
    ref = best["pressure_only_reference"]
    rows = [{"variant": name, "particles": len(solvers[name].x), "ms_per_step": 1e3 * t,
             "ratio_to_reference": t / ref, "threads": nb.get_num_threads(),
             "forces_asm_bytes": asm.get(name)} for name, t in best.items()]
    for r in rows:
        print(f"{r['variant']:>26}  {r['ms_per_step']:7.2f} ms/step  x{r['ratio_to_reference']:.3f}  "
              f"asm {r['forces_asm_bytes']}")
    out = Path(__file__).parent / "results" / "effects.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
