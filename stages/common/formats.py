"""Artifact file formats shared between stages (internal; studio-facing output is OpenUSD).

Units contract: every artifact is in the scene's units and up axis (``scene.units``): positions,
lengths, spacings, support radii in scene units, velocities in scene units per second. Physical
material quantities stay SI in every artifact: density kg/m^3, mass kg, pressure Pa (and, in the
config, viscosity Pa s, gravity m/s^2). The solvers work wholly in SI (simulate/driver.py converts
lengths in and out). A quantity mixing the two, the particle volume m / rho, is converted in one
place: ``ParticleMeta.volume`` gives it in scene units^3.

simulate  -> ``particles`` artifact folder:
    meta.json                 ParticleMeta (spacing, mass, rho0, fps, frame count, units, solver stats)
    frames/00000.npz ...      one file per output frame: x (N,3) f32 scene units (f64 far from the
                              origin: position_dtype), v (N,3) f32 scene
                              units/s, rho (N,) f32 kg/m^3, p (N,) f32 Pa, id (N,) i32
                              (N may change between frames)
    particles.usdc            the same frames as time-sampled UsdGeom.Points (studio-facing)
surface_extract / wall_snap -> per-frame artifact folders, each with
    surface_00012.npz         vertices (V,3) f32 scene units, faces (F,3) i32, normals (V,3) f32
mesh_import -> ``walls`` artifact folder:
    walls.npz                 vertices (V,3) f64 world space, scene units; faces (F,3) i32;
                              wall_id (F,) i32 (index into walls.json)
    walls.json                [{"name", "fluid": "inside"|"outside"|"both", "source" (the file as the config
                              names it, relative to its folder; "builtin:<kind>"), "report": {...},
                              "shell": thickness (scene units; only for a shell, whose fluid is "both"),
                              "motion": {"times": (K,) s, "translate": (K, 3) scene units, "quat": (K, 4)
                              w x y z, "pivot": (3,) scene units} (only for a moving wall: RigidMotion.to_json,
                              stages/common/motion.py; its vertices above are in its rest pose)}, ...]
    walls.usdc                the wall meshes as UsdGeom.Mesh prims (studio-facing; a moving wall in its
                              rest pose: export's walls layer carries the animation)
sdf_bake -> ``sdf`` artifact folder: sdf.npz, the static walls (see stages/common/sdf.py); with moving walls
    also bodies.json and bodies/<k>.npz, each moving wall alone in its rest pose (sdf.load_bodies)
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from stages.common.motion import RigidMotion

META_FILE = "meta.json"
FRAMES_DIR = "frames"


@dataclass
class ParticleMeta:
    spacing: float  # particle spacing l0, scene units
    mass: float  # particle mass, kg (SI: the solver's lattice mass)
    density: float  # rest density rho0, kg/m^3
    support: float  # kernel support radius h, scene units
    fps: float
    frame_count: int
    up_axis: str
    meters_per_unit: float  # metres per scene unit of every length in the artifact
    solver: str
    stats: dict[str, Any] = field(default_factory=dict)
    gravity: float | None = None  # |g| of the gravity effect, m/s^2 (0 without one; None: not recorded)

    def volume(self, rho: np.ndarray | float) -> np.ndarray:
        """Particle volume m / rho in scene units^3, for densities ``rho`` in kg/m^3 (m / rho is in m^3;
        a consumer that mixes it with positions and radii in scene units needs it in scene units^3)."""
        return self.mass / (np.asarray(rho, np.float64) * self.meters_per_unit ** 3)

    def save(self, folder: Path) -> None:
        (Path(folder) / META_FILE).write_text(json.dumps(asdict(self), indent=2, sort_keys=True))

    @classmethod
    def load(cls, folder: Path) -> "ParticleMeta":
        return cls(**json.loads((Path(folder) / META_FILE).read_text()))


@dataclass
class ParticleFrame:
    x: np.ndarray  # (N, 3) positions, scene units (SI inside a solver)
    v: np.ndarray  # (N, 3) velocities, scene units/s (SI inside a solver)
    rho: np.ndarray  # (N,) density, kg/m^3
    p: np.ndarray  # (N,) pressure, Pa
    id: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def frame_path(folder: Path, frame: int) -> Path:
    return Path(folder) / FRAMES_DIR / f"{frame:05d}.npz"


# Positions are stored as float32 where its rounding stays below this fraction of the scene's length scale
# (the particle spacing, the surface's cell), else as float64: float32's step is 2^-23 of the coordinate, so
# far from the origin (a survey or CAD scene 1e5 m out: 8 mm steps, 0.4 spacings at 2 cm) float32 quantised
# the particles, bent the surface (-12 % volume) and put snapped vertices 3 mm outside the walls.
PRECISION = 1e-4


def position_dtype(points: np.ndarray, scale: float | None) -> type:
    """np.float32 where storing ``points`` (N, 3) as float32 keeps them within PRECISION * ``scale`` (every
    scene within ~1,700 spacings of its origin), else np.float64. ``scale`` None: float32."""
    a = np.asarray(points)
    if scale is None or a.size == 0:
        return np.float32
    return np.float32 if float(np.abs(a).max()) * 2.0 ** -24 <= PRECISION * float(scale) else np.float64


def local_origin(lo, hi, scale: float) -> np.ndarray | None:
    """Where points between ``lo`` and ``hi`` are written relative to, for formats that hold float32 only
    (USD's point3f; the offset goes into a double-precision translate op): None where float32 in place is
    precise enough (position_dtype), else the box's centre."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if position_dtype(np.stack([lo, hi]), scale) is np.float32:
        return None
    return 0.5 * (lo + hi)


def save_particle_frame(folder: Path, frame: int, f: ParticleFrame, spacing: float | None = None) -> Path:
    """``spacing``: the scene's particle spacing, which decides the positions' precision (position_dtype)."""
    path = frame_path(folder, frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, x=f.x.astype(position_dtype(f.x, spacing)), v=f.v.astype(np.float32), rho=f.rho.astype(np.float32),
             p=f.p.astype(np.float32), id=f.id.astype(np.int32))
    return path


def load_particle_frame(folder: Path, frame: int) -> ParticleFrame:
    with np.load(frame_path(folder, frame)) as z:
        return ParticleFrame(x=z["x"], v=z["v"], rho=z["rho"], p=z["p"], id=z["id"])


@dataclass
class SurfaceMesh:
    vertices: np.ndarray  # (V, 3) float32 (float64 far from the origin: position_dtype)
    faces: np.ndarray  # (F, 3) int32, counter-clockwise seen from the air side
    normals: np.ndarray  # (V, 3) float32, pointing out of the fluid

    @classmethod
    def empty(cls) -> "SurfaceMesh":
        return cls(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32))


def surface_file(frame: int) -> str:
    return f"surface_{frame:05d}.npz"


def save_surface(folder: Path, frame: int, m: SurfaceMesh, scale: float | None = None) -> Path:
    """``scale``: the surface's cell (or the spacing), which decides the vertices' precision (position_dtype)."""
    path = Path(folder) / surface_file(frame)
    np.savez(path, vertices=m.vertices.astype(position_dtype(m.vertices, scale)), faces=m.faces.astype(np.int32),
             normals=m.normals.astype(np.float32))
    return path


def load_surface(folder: Path, frame: int) -> SurfaceMesh:
    with np.load(Path(folder) / surface_file(frame)) as z:
        return SurfaceMesh(vertices=z["vertices"], faces=z["faces"], normals=z["normals"])


WALLS_FILE = "walls.npz"
WALLS_INFO = "walls.json"


@dataclass
class WallMesh:
    vertices: np.ndarray  # (V, 3) float64, world space, scene units
    faces: np.ndarray  # (F, 3) int32
    wall_id: np.ndarray  # (F,) int32
    walls: list[dict[str, Any]]  # per wall: name, fluid ("inside"/"outside"/"both"), source, report, [shell], [motion]
    # (F,) bool: the faces of a shell wall's closed parts, which mesh_import made solids (an open tank and a rock in
    # one file); None: no such face. The bake folds them in as a solid, the snap puts the surface on them
    solid: np.ndarray | None = None

    def shell_thickness(self, default: float = 0.0) -> np.ndarray:
        """(walls,) float64: each wall's shell thickness as imported (scene units; ``default`` where the
        import left it open), 0 for a solid."""
        return np.array([0.0 if w.get("fluid") != "both" else default if w.get("shell") is None else float(w["shell"])
                         for w in self.walls], np.float64)

    def face_shells(self, shells: np.ndarray) -> np.ndarray:
        """(F,) each face's shell thickness from ``shells`` (per wall), 0 on the solid faces of a shell wall."""
        out = np.asarray(shells, np.float64)[self.wall_id]
        if self.solid is not None:
            out[self.solid] = 0.0
        return out

    def subset(self, keep: np.ndarray) -> "WallMesh":
        """The faces ``keep`` (a mask or indices) with every vertex and the whole walls list, so per-wall arrays
        keep their indices."""
        return WallMesh(self.vertices, self.faces[keep], self.wall_id[keep], self.walls,
                        None if self.solid is None else self.solid[keep])

    def motions(self) -> list[tuple[int, RigidMotion]]:
        """(wall index, motion) of every moving wall."""
        return [(i, RigidMotion.from_json(w["motion"])) for i, w in enumerate(self.walls) if w.get("motion") is not None]

    def posed(self, t: float) -> "WallMesh":
        """The walls at time ``t`` (s): every moving wall's vertices moved from its rest pose to its pose
        then (each wall has vertices of its own); ``self`` when no wall moves."""
        moving = self.motions()
        if not moving:
            return self
        v = self.vertices.copy()
        for i, m in moving:
            idx = np.unique(self.faces[self.wall_id == i])
            v[idx] = m.to_world(self.vertices[idx], t)
        return WallMesh(v, self.faces, self.wall_id, self.walls, self.solid)

    def save(self, folder: Path) -> None:
        extra = {} if self.solid is None or not self.solid.any() else {"solid": self.solid.astype(np.bool_)}
        np.savez(Path(folder) / WALLS_FILE, vertices=self.vertices.astype(np.float64),
                 faces=self.faces.astype(np.int32), wall_id=self.wall_id.astype(np.int32), **extra)
        (Path(folder) / WALLS_INFO).write_text(json.dumps(self.walls, indent=2, sort_keys=True))

    @classmethod
    def load(cls, folder: Path) -> "WallMesh":
        with np.load(Path(folder) / WALLS_FILE) as z:
            v, f, w = z["vertices"], z["faces"], z["wall_id"]
            solid = z["solid"] if "solid" in z.files else None
        return cls(v, f, w, json.loads((Path(folder) / WALLS_INFO).read_text()), solid)


def skipped_frame_marker(folder: Path, frame: int) -> Path:
    """The render stage's mark of a frame it skipped (``every``), which the movie tells from a lost one. A
    dotfile: bookkeeping of the cache entry, not published with the frames."""
    return Path(folder) / f".frame_{frame:05d}.skipped"
