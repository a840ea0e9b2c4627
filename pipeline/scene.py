"""Typed models of a scene config: units, frames, walls, fluid emitters, effects, outputs.

Every model forbids unknown keys and documents its unit, so a misspelt key is an error that names it,
never a value silently ignored. Stage parameters live with each stage (``Stage.Params``); this module
holds only the scene description that several stages share.
"""
from __future__ import annotations

import math
import posixpath
import re
from types import UnionType
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import (AfterValidator, BaseModel, ConfigDict, Discriminator, Field, Tag, ValidationInfo, field_validator,
                      model_validator)
from pydantic_core import InitErrorDetails, PydanticCustomError, ValidationError

Vec3 = tuple[float, float, float]


class InputFileMarker:
    """Marks a config field holding a path (relative to the config file) to a file a stage reads. The
    engine finds every such field in what a stage declares it reads (and in its params) and hashes the
    file's content into the stage's key, so no stage has to remember to name its input files."""

    def __repr__(self) -> str:
        return "InputFile"


def _normal_path(path: str | None) -> str | None:
    """One spelling per file ('./a//b.obj' is 'a/b.obj'): the path is part of the key, and another spelling of
    the same file re-ran everything from the stage that reads it."""
    if path and "\0" in path:  # the OS refuses it: a ValueError deep in the plan, exit 1 with no config line
        raise ValueError("a file name cannot hold a NUL character (\\0)")
    return posixpath.normpath(path) if path else path


INPUT_FILE = InputFileMarker()
InputFile = Annotated[str, AfterValidator(_normal_path), INPUT_FILE]
OptionalInputFile = Annotated[Union[str, None], AfterValidator(_normal_path), INPUT_FILE]


def _admits_bool(tp: Any) -> bool:
    if tp is bool or tp is Any:
        return True
    if get_origin(tp) is Literal:
        return any(isinstance(a, bool) for a in get_args(tp))
    if get_origin(tp) is Annotated:
        return _admits_bool(get_args(tp)[0])
    if get_origin(tp) in (Union, UnionType):
        return any(_admits_bool(a) for a in get_args(tp))
    return tp not in (int, float, type(None))


def _sequence_of(tp: Any) -> Any:
    """The list or tuple type inside an optional or annotated field type, else None."""
    if get_origin(tp) in (list, tuple):
        return tp
    if get_origin(tp) is Annotated:
        return _sequence_of(get_args(tp)[0])
    if get_origin(tp) in (Union, UnionType):
        return next((q for q in map(_sequence_of, get_args(tp)) if q is not None), None)
    return None


def _element(seq: Any, k: int) -> Any:
    args = get_args(seq)
    if not args:
        return Any
    if get_origin(seq) is list or (len(args) == 2 and args[1] is Ellipsis):
        return args[0]
    return args[k] if k < len(args) else Any


def bool_for_a_number(tp: Any, v: Any) -> bool:
    """Whether ``v`` puts a true/false where field type ``tp`` wants a number (pydantic reads True as 1: a
    ``count: true`` ran one frame), in a list or tuple of numbers too."""
    if isinstance(v, bool):
        return not _admits_bool(tp)
    seq = _sequence_of(tp) if isinstance(v, (list, tuple)) else None
    return seq is not None and any(isinstance(x, bool) and not _admits_bool(_element(seq, k)) for k, x in enumerate(v))


def no_bool_for_a_number(cls, v: Any, info: ValidationInfo) -> Any:
    """The config models' before-validator of every field (``field_validator("*", mode="before")``)."""
    if info.field_name is not None and bool_for_a_number(cls.model_fields[info.field_name].annotation, v):
        raise ValueError("expected a number, not true/false")
    return v


class Model(BaseModel):
    # NaN/inf are never a valid placement, velocity, centre, size or spacing: one line naming the field
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    _no_bool_for_a_number = field_validator("*", mode="before")(classmethod(no_bool_for_a_number))


def _finite(v: Vec3) -> Vec3:
    if not all(math.isfinite(c) for c in v):
        raise ValueError("expected finite numbers")
    return v


# -- scene -------------------------------------------------------------------------------------
class Units(Model):
    meters_per_unit: float = Field(1.0, gt=0, description="metres per scene unit (1.0 = metres)")
    up_axis: Literal["Y", "Z"] = Field("Z", description="the scene's up axis; gravity points against it")


class Frames(Model):
    fps: float = Field(30.0, gt=0, le=10000, description="output frames per second")
    count: int = Field(60, ge=1, le=1_000_000, description="number of output frames (frame 0 is the start)")


class Domain(Model):
    min: Vec3 = Field(description="lower corner of the simulation domain, scene units")
    max: Vec3 = Field(description="upper corner of the simulation domain, scene units")

    _fin = field_validator("min", "max")(_finite)

    @model_validator(mode="after")
    def _ordered(self) -> "Domain":
        if any(a >= b for a, b in zip(self.min, self.max)):
            raise ValueError("min must be below max on every axis")
        return self


class Scene(Model):
    # a plain folder name: no separators, no leading dot (so never '.', '..' or a hidden staging name)
    name: str = Field(description="scene name; also the output folder name (letters, digits, _ . -; not starting with '.')")
    units: Units = Field(default_factory=Units)
    frames: Frames = Field(default_factory=Frames)
    domain: Domain | None = Field(None, description="simulation domain; default: the walls' bounds")

    @field_validator("name")
    @classmethod
    def _plain_folder_name(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9_-][A-Za-z0-9_.-]{0,63}", v):
            raise ValueError("not a plain folder name (it names the output folder): 1-64 ASCII letters "
                             "(a-z, A-Z), digits, _ . -, not starting with '.'")
        return v


# -- walls -------------------------------------------------------------------------------------
class Placement(Model):
    scale: float | Vec3 = Field(1.0, description="uniform or per-axis scale, applied first")
    rotate: Vec3 = Field((0.0, 0.0, 0.0), description="rotation in degrees about X, then Y, then Z")
    translate: Vec3 = Field((0.0, 0.0, 0.0), description="translation in scene units, applied last")
    fit: Domain | None = Field(None, description="uniformly scale and move the model to fit this box")

    @field_validator("scale")
    @classmethod
    def _non_zero(cls, v: float | Vec3) -> float | Vec3:
        # a zero flattens the model to nothing, found only in mesh_import ("empty mesh after removing degenerate
        # faces"); a negative scale is a mirror
        if any(c == 0 for c in (v if isinstance(v, tuple) else (v,))):
            raise ValueError("must be non-zero (a negative scale mirrors the model)")
        return v


class Keyframe(Model):
    time: float = Field(description="seconds")
    translate: Vec3 = Field((0.0, 0.0, 0.0), description="offset of the pivot from its rest position, scene units")
    rotate: Vec3 = Field((0.0, 0.0, 0.0), description="rotation about the pivot from the rest pose, degrees "
                         "about X, then Y, then Z (as the placement's rotate)")

    _fin = field_validator("translate", "rotate")(_finite)


class Motion(Model):
    """A rigid wall's animation relative to its placed rest pose: the translation is interpolated
    linearly, the rotation by slerp (the short way: keys less than half a turn apart); held before the
    first and after the last key."""

    keyframes: list[Keyframe] = Field(min_length=1, description="the poses at given times, times strictly increasing")
    pivot: Vec3 | None = Field(None, description="rest position of the rotation centre, scene units; default: the "
                               "centre of the wall's bounding box at rest")

    _fin = field_validator("pivot")(lambda v: v if v is None else _finite(v))

    @field_validator("keyframes")
    @classmethod
    def _increasing(cls, v: list[Keyframe]) -> list[Keyframe]:
        for a, b in zip(v, v[1:]):
            if not b.time > a.time:
                raise ValueError(f"keyframe times must be strictly increasing (time {b.time} follows {a.time})")
            # slerp goes the short way: [0, 200, 0] after [0, 0, 0] turned 160 degrees the other way, silently
            step = max(abs(q - p) for p, q in zip(a.rotate, b.rotate))
            turn = _turn_degrees(a.rotate, b.rotate)
            if step >= 180.0 or turn > 179.0:
                # angles written wrapped (162 then -144): the same angle one turn on, nearer the last key, is what
                # a user who meant the short way must write; adding a key in between would keep the long way
                near = [q - 360.0 * round((q - p) / 360.0) for p, q in zip(a.rotate, b.rotate)]
                wrapped = (f"; for the short way write rotate {[float(f'{x:g}') for x in near]} (angles are not "
                           "wrapped), for the long way" if max(abs(q - p) for p, q in zip(a.rotate, near)) < 180.0
                           else "; so")
                raise ValueError(f"keyframes at {a.time:g} s and {b.time:g} s are {max(step, turn):g} degrees apart: "
                                 f"the rotation between keys takes the shorter way round ({turn:.0f} degrees){wrapped} "
                                 "keep keys under a half turn apart (add one in between)")
        return v


def _rotation(deg: Vec3) -> list[list[float]]:
    """The rotation matrix of ``rotate`` (degrees about X, then Y, then Z): Rz Ry Rx."""
    cx, cy, cz = (math.cos(math.radians(a)) for a in deg)
    sx, sy, sz = (math.sin(math.radians(a)) for a in deg)
    rx = [[1, 0, 0], [0, cx, -sx], [0, sx, cx]]
    ry = [[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]
    rz = [[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]]
    mul = lambda a, b: [[sum(a[i][k] * b[k][j] for k in range(3)) for j in range(3)] for i in range(3)]  # noqa: E731
    return mul(rz, mul(ry, rx))


def _turn_degrees(a: Vec3, b: Vec3) -> float:
    """The angle of the rotation taking pose ``a`` to pose ``b`` (0-180 degrees)."""
    ra, rb = _rotation(a), _rotation(b)
    trace = sum(ra[k][i] * rb[k][i] for i in range(3) for k in range(3))  # trace(Ra^T Rb)
    return math.degrees(math.acos(max(-1.0, min(1.0, 0.5 * (trace - 1.0)))))


class WallPlacement(Placement):
    motion: Motion | None = Field(None, description="rigid animation of the wall (default: it stands still)")


class BuiltinWall(WallPlacement):
    builtin: Literal["box_tank", "open_box", "cylinder", "plane"] = Field(
        description="analytic wall: box_tank (closed box, fluid inside), open_box (no lid), "
        "cylinder (closed, fluid inside), plane (floor through the origin)")
    size: Vec3 = Field((1.0, 1.0, 1.0), description="box extent in scene units (cylinder: diameter, diameter, height)")
    center: Vec3 = Field((0.0, 0.0, 0.0), description="centre of the box's footprint at its floor, scene units")
    fluid: Literal["inside", "outside"] = Field("inside", description="which side of the wall the fluid is on")

    @field_validator("size")
    @classmethod
    def _positive(cls, v: Vec3) -> Vec3:
        if not all(math.isfinite(c) and c > 0 for c in v):
            raise ValueError("expected three positive sizes")
        return v


class Shell(Model):
    """A wall that is its surface thickened on both sides: every point within thickness/2 of the mesh is
    wall, so an open bowl, a sheet or a single-sided trough holds fluid on either side."""

    thickness: float | None = Field(None, gt=0, description="shell thickness, scene units; default "
                                    "0.6 fluid spacings (the least sdf_bake proves leak-free at its default cell)")


class MeshWall(WallPlacement):
    """A wall read from a model: a solid (``fluid``: which side is fluid) or a ``shell``. With neither
    set, mesh_import chooses: a closed mesh is a solid obstacle (fluid outside), an open one (boundary
    edges) a shell."""

    fluid: Literal["inside", "outside"] | None = Field(
        None, description="outside: a solid obstacle; inside: a container; default: outside for a closed mesh, "
        "a shell for an open one")
    shell: Shell | None = Field(None, description="treat the mesh as a thin shell (fluid on both sides)")

    @model_validator(mode="after")
    def _solid_or_shell(self) -> "MeshWall":
        if self.fluid is not None and self.shell is not None:
            raise ValueError("a wall is either a solid ('fluid: inside/outside') or a 'shell', not both")
        return self


MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")


def _format_check(suffixes: tuple[str, ...], what: str, other_key: tuple[str, tuple[str, ...], str] | None = None):
    """A validator of a model file's extension: one line naming the formats read, and for the DCC formats
    studios also use (FBX, Alembic, Blender, Maya) the way in (the file was found unreadable only when the
    import ran, with a USD library error for an .abc); ``other_key`` (key, its suffixes, what): the key that
    takes this file instead (a wall's ``file: x.usda`` wants ``usd: x.usda``)."""
    def check(path: str) -> str:
        suffix = posixpath.splitext(path)[1].lower()
        if suffix not in suffixes:
            other = (f"; {suffix} is read by neither: export it from the DCC as USD, OBJ or glTF"
                     if suffix in (".fbx", ".abc", ".blend", ".ma", ".mb", ".max", ".c4d", ".3ds", ".dae") else "")
            if other_key is not None and suffix in other_key[1]:
                other = f"; for {other_key[2]} use `{other_key[0]}: {path}`"
            raise ValueError(f"expected {what} ({', '.join(suffixes)}){other}")
        return path
    return check


class FileWall(MeshWall):
    file: InputFile = Field(description="OBJ/PLY/STL/OFF/GLB/GLTF path, relative to the config file")
    meters_per_unit: float | None = Field(None, gt=0, description="the file's units if not the scene's (GLB/GLTF: "
                                          "metres, as the format specifies)")
    up_axis: Literal["Y", "Z"] | None = Field(None, description="the file's up axis if not the scene's (GLB/GLTF: Y, "
                                              "as the format specifies; an OBJ from a Y-up package: Y)")

    _mesh = field_validator("file")(_format_check(MESH_SUFFIXES, "a mesh file", ("usd", USD_SUFFIXES, "USD")))


class UsdWall(MeshWall):
    usd: InputFile = Field(description=".usda/.usdc/.usdz path, relative to the config file")
    prims: list[str] = Field(default_factory=lambda: ["/**"], description="prim paths or glob patterns to use as walls")
    include_invisible: bool = Field(False, description="also use prims whose visibility is 'invisible'")
    subdivide: int = Field(0, ge=0, le=4, description="refine subdivision cages (a mesh's subdivisionScheme "
                           "catmullClark, USD's fallback, or loop) this many levels, to the smooth surface a "
                           "renderer draws; 0: the cage as-is (recorded in the walls report)")

    _usd = field_validator("usd")(_format_check(USD_SUFFIXES, "a USD file", ("file", MESH_SUFFIXES, "a mesh file")))


def _kind_by_key(*keys: str):
    """A union discriminator that picks the model by which of ``keys`` the mapping has."""

    def pick(v: object) -> str | None:
        if isinstance(v, BaseModel):
            v = v.model_dump()
        if isinstance(v, dict):
            for k in keys:
                if k in v:
                    return k
        return None

    return pick


Wall = Annotated[
    Union[Annotated[BuiltinWall, Tag("builtin")], Annotated[FileWall, Tag("file")], Annotated[UsdWall, Tag("usd")]],
    Discriminator(_kind_by_key("builtin", "file", "usd"),
                  custom_error_type="wall_kind",
                  custom_error_message="a wall needs one of the keys 'builtin', 'file' or 'usd'"),
]


# -- fluid -------------------------------------------------------------------------------------
class Emitter(Model):
    velocity: Vec3 = Field((0.0, 0.0, 0.0), description="initial velocity, scene units per second")


class BoxEmitter(Emitter):
    box: Domain = Field(description="fill this axis-aligned box with particles on a cubic lattice")


class SphereEmitter(Emitter):
    sphere: "SphereSpec"


class SphereSpec(Model):
    center: Vec3
    radius: float = Field(gt=0, description="scene units")


class MeshEmitter(Emitter, Placement):
    mesh: InputFile = Field(description="fill the interior of this mesh file (relative to the config): OBJ/PLY/STL/"
                            "OFF/GLB/GLTF, or USD (.usd/.usda/.usdc/.usdz: its world transforms, metersPerUnit and upAxis "
                            "apply)")
    meters_per_unit: float | None = Field(None, gt=0, description="the file's units if not the scene's (GLB/GLTF: "
                                          "metres, as the format specifies; not for USD, which states its own)")
    up_axis: Literal["Y", "Z"] | None = Field(None, description="the file's up axis if not the scene's (GLB/GLTF: Y; "
                                              "not for USD, which states its own)")
    prims: list[str] = Field(default_factory=lambda: ["/**"], description="USD only: prim paths or glob patterns of "
                             "the meshes to fill")

    _mesh = field_validator("mesh")(_format_check(MESH_SUFFIXES + USD_SUFFIXES, "a mesh or USD file"))

    @model_validator(mode="after")
    def _usd_states_its_units(self) -> "MeshEmitter":
        if self.meters_per_unit is not None and is_usd(self.mesh):
            raise ValueError("meters_per_unit: a USD file states its own (metersPerUnit); leave it out")
        if self.up_axis is not None and is_usd(self.mesh):
            raise ValueError("up_axis: a USD file states its own (upAxis); leave it out")
        return self


def is_usd(path: str) -> bool:
    return path.lower().endswith(USD_SUFFIXES)


SphereEmitter.model_rebuild()

EmitterSpec = Annotated[
    Union[Annotated[BoxEmitter, Tag("box")], Annotated[SphereEmitter, Tag("sphere")], Annotated[MeshEmitter, Tag("mesh")]],
    Discriminator(_kind_by_key("box", "sphere", "mesh"),
                  custom_error_type="emitter_kind",
                  custom_error_message="an emitter needs one of the keys 'box', 'sphere' or 'mesh'"),
]


class Inflow(Model):
    """A continuous emitter (a tap, a nozzle): a round jet leaving the disc of ``radius`` around ``center``
    normal to ``direction`` at ``speed``, at the volume rate pi radius^2 speed from ``start`` to ``end``
    (stages/simulate/inflow.py)."""

    center: Vec3 = Field(description="centre of the emitting disc, scene units")
    direction: Vec3 = Field(description="the jet's direction (normalised; not zero)")
    radius: float = Field(gt=0, description="radius of the jet, scene units (at least the fluid spacing)")
    speed: float = Field(gt=0, description="jet speed, scene units per second")
    start: float = Field(0.0, ge=0, description="when the jet starts, seconds")
    end: float | None = Field(None, gt=0, description="when the jet stops, seconds; default: the end of the shot")
    attach: int | None = Field(None, ge=0, description="index into walls of the wall the nozzle rides on (a nozzle on "
                               "an animated prop): center and direction are given at time 0 and move rigidly with it, "
                               "and the jet leaves with the wall's velocity added; default: fixed in the scene")

    _fin = field_validator("center")(_finite)

    @field_validator("direction")
    @classmethod
    def _unit(cls, v: Vec3) -> Vec3:
        n = math.sqrt(sum(c * c for c in v)) if all(math.isfinite(c) for c in v) else 0.0
        if not n > 0:
            raise ValueError("expected a finite non-zero vector")
        return (v[0] / n, v[1] / n, v[2] / n)

    @model_validator(mode="after")
    def _ordered(self) -> "Inflow":
        if self.end is not None and self.end <= self.start:
            raise ValueError(f"end ({self.end:g} s) must be after start ({self.start:g} s)")
        return self


class Sink(Model):
    """A drain: particles whose centre enters the box are removed (counted as 'sunk' in the statistics)."""

    box: Domain = Field(description="the sink's axis-aligned box, scene units")


class Fluid(Model):
    spacing: float = Field(gt=0, description="particle spacing l0, scene units")
    density: float = Field(1000.0, gt=0, description="rest density rho0, kg/m^3")
    # before the emitters: their check needs to know whether a jet fills the scene instead
    inflow: list[Inflow] = Field(default_factory=list, description="continuous emitters (jets) adding fluid during the run")
    sinks: list[Sink] = Field(default_factory=list, description="boxes that remove the fluid entering them (drains)")
    emitters: list[EmitterSpec] = Field(
        default_factory=list, validate_default=True,
        description="where the fluid starts: box, sphere or mesh volumes (none if an inflow fills the scene)")
    settle: float = Field(0.0, ge=0, le=60, description="seconds the fluid settles before t = 0, its velocities "
                          "set to zero 30 times a second (a fluid that starts at rest; 0 = off): the start lattice "
                          "creeps into its resting packing there instead of during the shot")

    @field_validator("inflow")
    @classmethod
    def _wide_enough(cls, v: list[Inflow], info) -> list[Inflow]:
        l0 = info.data.get("spacing")
        for i, jet in enumerate(v):
            if l0 is not None and jet.radius < l0:
                raise ValueError(f"inflow {i}: radius {jet.radius:g} is below the spacing {l0:g} "
                                 "(a jet needs a few particles across)")
        return v

    @field_validator("emitters")
    @classmethod
    def _some_fluid(cls, v: list, info) -> list:
        if not v and not info.data.get("inflow"):
            raise ValueError("needs at least one emitter (or a fluid.inflow)")
        return v


# -- effects (issue 8: only the declared ones are compiled in and computed) --------------------
class Gravity(Model):
    """Uniform gravity along the scene's down axis."""

    g: float = Field(9.81, ge=0, description="magnitude, m/s^2, pointing against the up axis")

    @field_validator("g", mode="before")
    @classmethod
    def _a_size(cls, v):
        if isinstance(v, (list, tuple)):  # SPlisHSPlasH and Houdini take a vector
            raise ValueError("gravity points against scene.units.up_axis: give its size in m/s^2 (9.81), not a "
                             "vector")
        return v


class Viscosity(Model):
    """Fluid-fluid viscosity (PHYSICS.md eq. 7, 9) and the resting wall's no-slip term (eq. 13-15)."""

    mu: float = Field(0.001, ge=0, description="dynamic viscosity, Pa s (water 0.001)")
    wall: bool = Field(True, description="also the no-slip wall term of the seed method (eq. 13-15)")


class SurfaceTension(Model):
    """Akinci et al. 2013: cohesion (spline C(r)) + curvature (particle normals), both scaled by the
    symmetric correction K_ij = 2 rho0 / (rho_i + rho_j). ``gamma`` is converted to the model's
    constant with the Kirkwood-Buff integral of the cohesion pair force over a uniform fluid."""

    gamma: float = Field(0.0728, ge=0, le=10.0, description="surface tension coefficient, N/m (water 0.0728; at most "
                         "10, 4 x any liquid's (molten metals 1-2.5): the sound speed and the step follow sqrt(gamma))")


class WallAdhesion(Model):
    """Akinci et al. 2013 adhesion towards the walls: the adhesion kernel A(r) integrated over the wall
    half-space at the particle's SDF distance, pulling along the SDF normal towards the wall."""

    beta: float = Field(0.5, ge=0, description="adhesion strength, dimensionless: 1 pulls like the fluid's own "
                        "cohesion (surface_tension.gamma, or water's 0.0728 N/m when surface_tension is absent)")


class WallFriction(Model):
    """Tangential velocity of particles in wall contact (SDF distance below h/2, one spacing at the default
    support, fading to 0 at the support radius h) decays as exp(-rate t): an acceleration -rate v_t, so
    the result does not depend on the time step (which is kept below 0.5 / rate)."""

    rate: float = Field(5.0, ge=0, description="decay rate of the tangential velocity at wall contact, 1/s")


class Wind(Model):
    """Drag towards the air velocity on free-surface particles (density below 0.97 rho0, ramping to full
    drag at 0.77 rho0)."""

    velocity: Vec3 = Field(description="air velocity, scene units/s")
    drag: float = Field(1.0, ge=0, description="relaxation rate towards the air velocity, 1/s")

    _fin_velocity = field_validator("velocity")(_finite)


class Attractor(Model):
    """Point attraction a = strength (u / r)^2 towards ``point`` (u = one scene unit), softened as
    strength u^2 r / (r^2 + s^2)^(3/2) within the softening radius s."""

    point: Vec3 = Field(description="attraction centre, scene units")
    strength: float = Field(description="acceleration at one scene unit of distance, m/s^2 (negative repels)")
    softening: float | None = Field(None, gt=0, description="softening radius s, scene units; default 2 fluid spacings")

    _finite_point = field_validator("point")(_finite)

    @field_validator("strength")
    @classmethod
    def _finite_strength(cls, v: float) -> float:
        if not math.isfinite(v):
            raise ValueError("expected a finite number")
        return v


class Effects(Model):
    """The forces a scene declares; only these are compiled into the solver's kernels (pressure is
    always on). Solvers work in SI: scene lengths are converted with units.meters_per_unit."""

    gravity: Gravity | None = None
    viscosity: Viscosity | None = None
    surface_tension: SurfaceTension | None = None
    wall_adhesion: WallAdhesion | None = None
    wall_friction: WallFriction | None = None
    wind: Wind | None = None
    attractor: Attractor | None = None

    def enabled(self) -> tuple[str, ...]:
        return tuple(name for name in type(self).model_fields if getattr(self, name) is not None)


class Camera(Model):
    """The shot's camera, used by render (the frames) and export (the USD camera prim)."""

    usd: OptionalInputFile = Field(None, description="take the camera from this USD file (relative to the config file)")
    prim: str | None = Field(None, description="the UsdGeom.Camera prim in `usd`; default: the first camera found")

    @field_validator("usd")
    @classmethod
    def _usd_file(cls, v: str | None) -> str | None:
        return v if v is None else _format_check(USD_SUFFIXES, "a USD file")(v)
    position: Vec3 | None = Field(None, description="eye position, scene units; default: framed on the walls")
    focal_point: Vec3 | None = Field(None, description="point looked at, scene units; default: the walls' centre")
    up: Vec3 | None = Field(None, description="view up vector; default: the scene's up axis")
    view_angle: float = Field(30.0, gt=1, lt=170, description="vertical field of view, degrees (a USD camera's own wins)")
    # the shot's image size: render's frames and the exported USD camera's film back (so a portrait shot's
    # USD camera is not 16:9); a stage's own setting (render.resolution, export.camera_aspect) wins for it
    resolution: tuple[Annotated[int, Field(ge=16, le=8192)], Annotated[int, Field(ge=16, le=8192)]] | None = Field(
        None, description="image width and height, pixels, for render and the USD camera; default 1280 x 720")

    @field_validator("position", "focal_point", "up")
    @classmethod
    def _finite_vector(cls, v: Vec3 | None, info) -> Vec3 | None:
        if v is not None and not all(math.isfinite(c) for c in v):
            raise ValueError("expected finite numbers")
        if v is not None and info.field_name == "up" and not any(v):
            raise ValueError("expected a non-zero vector (the direction that is up in the frames)")
        return v

    @model_validator(mode="after")
    def _a_view(self) -> "Camera":
        """An eye on its focal point looks nowhere, and an up along the view direction leaves the roll
        undefined: both rendered blank frames."""
        if self.position is not None and self.focal_point is not None:
            view = [f - p for f, p in zip(self.focal_point, self.position)]
            if not any(view):
                raise ValueError("position and focal_point are the same point: the camera looks nowhere")
            if self.up is not None and _parallel(view, self.up):
                raise ValueError("up is along the view direction (position -> focal_point): give an up across it")
        return self


def _parallel(a, b) -> bool:
    cross = (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])
    return math.sqrt(sum(c * c for c in cross)) <= 1e-6 * math.sqrt(sum(c * c for c in a) * sum(c * c for c in b))


class SceneConfig(Model):
    """The scene part of a config (everything but ``stages``, ``outputs`` and ``config_version``)."""

    scene: Scene
    walls: list[Wall] = Field(default_factory=list, description="the wall models; the fluid region is where every wall allows it")
    fluid: Fluid | None = None
    effects: Effects = Field(default_factory=Effects)
    camera: Camera = Field(default_factory=Camera)

    @model_validator(mode="after")
    def _attached_to_a_wall(self) -> "SceneConfig":
        """An inflow's ``attach`` names one of the walls (one that does not move is fine: it stands still)."""
        for i, jet in enumerate(self.fluid.inflow if self.fluid is not None else ()):
            if jet.attach is not None and jet.attach >= len(self.walls):
                raise ValidationError.from_exception_data("SceneConfig", [InitErrorDetails(
                    type=PydanticCustomError("no_such_wall", "no wall {attach} to attach to: walls has {n} entries (from 0)",
                                             {"attach": jet.attach, "n": len(self.walls)}),
                    loc=("fluid", "inflow", i, "attach"), input=jet.attach)])
        return self

    @model_validator(mode="after")
    def _settles_at_rest(self) -> "SceneConfig":
        """Settling zeroes every velocity before t = 0: it is for a fluid at rest among walls at rest (a sink
        would drain it before the shot starts). Checked here, not when the simulation starts: the mistake
        then costs no import and bake first. (Walls animated in a USD file are refused by the solver.)"""
        fluid = self.fluid
        if fluid is None or fluid.settle <= 0:
            return self
        moving = next((i for i, w in enumerate(self.walls) if w.motion is not None), None)
        why = next((why for there, why in (
            (any(any(c != 0 for c in e.velocity) for e in fluid.emitters), "an emitter gives the fluid a velocity"),
            (fluid.inflow, "the scene has an inflow"), (fluid.sinks, "the scene has a sink"),
            (moving is not None, f"walls.{moving} moves")) if there), None)
        if why:
            raise ValidationError.from_exception_data("SceneConfig", [InitErrorDetails(
                type=PydanticCustomError("settle_not_at_rest", "for a fluid that starts at rest, but {why}; set it "
                                         "to 0", {"why": why}), loc=("fluid", "settle"), input=fluid.settle)])
        return self
