"""The rigid motion of one wall: keyframed translation of a pivot and rotation about it.

A moving wall is stored in its rest pose (its placed pose with zero motion); at time t a rest point
x goes to ``R(t) (x - pivot) + pivot + T(t)``. Between keyframes the translation is linear and the
rotation the shortest-arc slerp of the two keys' quaternions (so two keys must differ by less than
a half turn: a full turn needs at least three keys); before the first key and after the last the pose
is held. Lengths are in scene units in every artifact (``scaled`` converts to metres for a solver).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable

import numpy as np

from stages.common.placement import rotation_xyz


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """3x3 rotation of the unit quaternion (w, x, y, z)."""
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z), w >= 0, of the rotation matrix ``r`` (Shepperd's method)."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r)
    i = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    elif i == 1:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
    elif i == 2:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def _segment(q0: np.ndarray, q1: np.ndarray) -> tuple[np.ndarray, float]:
    """The shortest arc from ``q0`` to ``q1``: its unit axis in ``q0``'s body frame and its angle (rad).
    q(s) = q0 * (cos(s a/2), sin(s a/2) axis) for s in [0, 1]."""
    w0, v0 = q0[0], q0[1:]
    w1, v1 = q1[0], q1[1:]
    # q0^-1 q1 (q0 unit: its inverse is its conjugate)
    w = w0 * w1 + v0 @ v1
    v = w0 * v1 - w1 * v0 - np.cross(v0, v1)
    if w < 0:  # the same rotation the short way round
        w, v = -w, -v
    s = np.linalg.norm(v)
    angle = 2.0 * np.arctan2(s, w)
    axis = v / s if s > 0 else np.array([1.0, 0.0, 0.0])
    return axis, float(angle)


@dataclass
class RigidMotion:
    times: np.ndarray  # (K,) seconds, strictly increasing, K >= 1
    translate: np.ndarray  # (K, 3) offset of the pivot from its rest position, scene units
    quat: np.ndarray  # (K, 4) rotation (w, x, y, z), unit, from the rest pose
    pivot: np.ndarray  # (3,) rest position of the rotation centre, scene units

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, np.float64).reshape(-1)
        self.translate = np.asarray(self.translate, np.float64).reshape(-1, 3)
        q = np.asarray(self.quat, np.float64).reshape(-1, 4)
        self.quat = q / np.linalg.norm(q, axis=1, keepdims=True)
        self.pivot = np.asarray(self.pivot, np.float64).reshape(3)
        k = len(self.times)
        if k < 1 or len(self.translate) != k or len(self.quat) != k:
            raise ValueError(f"RigidMotion: {k} times, {len(self.translate)} translations, {len(self.quat)} rotations")
        if (np.diff(self.times) <= 0).any():
            raise ValueError("RigidMotion: times must be strictly increasing")
        # per key its rotation matrix, per segment its arc: a solver poses its walls every step
        self._rot = [quat_to_matrix(q) for q in self.quat]
        self._arc = [_segment(self.quat[i], self.quat[i + 1]) for i in range(k - 1)]

    # -- evaluation ----------------------------------------------------------------------------
    def _where(self, t: float) -> tuple[int, float] | None:
        """(segment i, fraction s in [0, 1)) of t inside the keyed span, None outside it."""
        ts = self.times
        if len(ts) < 2 or not (ts[0] <= t < ts[-1]):
            return None
        i = int(np.searchsorted(ts, t, side="right")) - 1
        return i, (t - ts[i]) / (ts[i + 1] - ts[i])

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (3,3), T (3,)) at time t: world = R @ (x_rest - pivot) + pivot + T. Translate linear,
        rotation slerp between keyframes; held before the first and after the last keyframe."""
        seg = self._where(float(t))
        if seg is None:
            k = 0 if t < self.times[0] else -1
            return self._rot[k].copy(), self.translate[k].copy()
        i, s = seg
        axis, angle = self._arc[i]
        r = self._rot[i] @ _axis_angle(axis, s * angle)
        return r, (1.0 - s) * self.translate[i] + s * self.translate[i + 1]

    def velocity(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(v (3,), omega (3,)): the pivot's velocity and the angular velocity (world frame, rad/s) at t,
        the exact derivative of pose() inside a segment (zero outside the keyed span; at a key, the
        segment that starts there)."""
        seg = self._where(float(t))
        if seg is None:
            return np.zeros(3), np.zeros(3)
        i, _ = seg
        dt = self.times[i + 1] - self.times[i]
        axis, angle = self._arc[i]
        # R(s) = R_i Rot(axis, s angle): R' R^T = (angle / dt) [R_i axis]x, constant over the segment
        return (self.translate[i + 1] - self.translate[i]) / dt, self._rot[i] @ axis * (angle / dt)

    def matrix(self, t: float) -> np.ndarray:
        """4x4 (column vectors) taking rest positions to world positions at t."""
        r, tr = self.pose(t)
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = self.pivot + tr - r @ self.pivot
        return m

    def rest_transform(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(A (3,3), b (3,)) with x_rest = A @ x_world + b at t (A = R^T, b = pivot - R^T (pivot + T)):
        what a kernel needs to sample the wall's rest-frame field at a world position."""
        r, tr = self.pose(t)
        return r.T.copy(), self.pivot - r.T @ (self.pivot + tr)

    def to_world(self, points: np.ndarray, t: float) -> np.ndarray:
        """Rest positions (N, 3) -> world positions at t."""
        r, tr = self.pose(t)
        return (np.asarray(points, np.float64) - self.pivot) @ r.T + self.pivot + tr

    def to_rest(self, points: np.ndarray, t: float) -> np.ndarray:
        """World positions (N, 3) at t -> the wall's rest frame: R^T (x - pivot - T) + pivot."""
        r, tr = self.pose(t)
        return (np.asarray(points, np.float64) - self.pivot - tr) @ r + self.pivot

    # -- conversions ---------------------------------------------------------------------------
    def scaled(self, k: float) -> "RigidMotion":
        """Every length times ``k`` (scene units -> metres with k = meters_per_unit)."""
        return RigidMotion(self.times.copy(), self.translate * k, self.quat.copy(), self.pivot * k)

    def swept_bounds(self, lo, hi) -> tuple[np.ndarray, np.ndarray]:
        """The box covering the rest box [lo, hi]'s 8 corners at every key and at >= 8 samples per
        segment (more for a large turn: one sample per 5 degrees, so a corner's arc bulges past the
        chord by less than 0.1 % of its radius)."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        corners = np.array([[(lo, hi)[(c >> a) & 1][a] for a in range(3)] for c in range(8)])
        times = [self.times]
        for i in range(len(self.times) - 1):
            _, angle = self._arc[i]
            n = max(8, int(np.ceil(np.degrees(angle) / 5.0)))
            times.append(np.linspace(self.times[i], self.times[i + 1], n + 1)[1:-1])
        pts = np.concatenate([self.to_world(corners, t) for t in np.concatenate(times)])
        return pts.min(axis=0), pts.max(axis=0)

    def to_json(self) -> dict[str, Any]:
        return {"times": self.times.tolist(), "translate": self.translate.tolist(), "quat": self.quat.tolist(),
                "pivot": self.pivot.tolist()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "RigidMotion":
        return cls(np.asarray(d["times"]), np.asarray(d["translate"]), np.asarray(d["quat"]), np.asarray(d["pivot"]))

    @classmethod
    def from_keyframes(cls, keyframes: Iterable[Any], pivot) -> "RigidMotion":
        """From the config's keyframes (models or dicts with ``time`` s, ``translate`` scene units and
        ``rotate`` degrees about X, then Y, then Z, as Placement.rotate) about ``pivot``."""
        ks = [k if isinstance(k, dict) else k.model_dump() for k in keyframes]
        return cls(np.array([float(k["time"]) for k in ks]),
                   np.array([k.get("translate", (0.0, 0.0, 0.0)) for k in ks], np.float64),
                   np.array([matrix_to_quat(rotation_xyz(k.get("rotate", (0.0, 0.0, 0.0)))) for k in ks]), pivot)

    @classmethod
    def from_matrices(cls, times, matrices, pivot, tol: float = 1e-6) -> "RigidMotion":
        """From 4x4 matrices (column vectors) taking rest positions to world positions at ``times``. The
        3x3 part is orthonormalised (polar decomposition); one that is not a rotation within ``tol``
        (a scale or shear, or a mirror) raises ValueError."""
        pivot = np.asarray(pivot, np.float64)
        quats, trans = [], []
        for m in matrices:
            m = np.asarray(m, np.float64)
            a = m[:3, :3]
            u, _, vt = np.linalg.svd(a)
            r = u @ vt
            if np.linalg.det(r) < 0 or np.abs(a - r).max() > tol * max(1.0, np.abs(a).max()):
                raise ValueError("the animation is not rigid (it scales, shears or mirrors)")
            quats.append(matrix_to_quat(r))
            trans.append(m[:3, 3] + r @ pivot - pivot)
        return cls(np.asarray(times, np.float64), np.array(trans), np.array(quats), pivot)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """3x3 rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def rest_transform(motion: RigidMotion, t: float) -> tuple[np.ndarray, np.ndarray]:
    """``motion.rest_transform(t)``: (A, b) with x_rest = A @ x_world + b."""
    return motion.rest_transform(t)



def reach(lo, hi, pivot) -> float:
    """The farthest a point of the box [lo, hi] (a wall's rest box) is from ``pivot``: times the angular
    speed it bounds the speed the rotation gives a point of the wall."""
    lo, hi, pivot = (np.asarray(a, np.float64) for a in (lo, hi, pivot))
    return float(np.linalg.norm(np.maximum(np.abs(lo - pivot), np.abs(hi - pivot))))


def top_wall_speed(motion, reach: float) -> float:
    """The fastest a wall point within ``reach`` of the pivot goes over the whole motion: the pivot's velocity
    and the angular velocity are constant over a segment, so the keys and the segments' midpoints cover it."""
    keys = np.asarray(motion.times, np.float64)
    ts = np.concatenate([keys, 0.5 * (keys[:-1] + keys[1:])])
    return max(wall_speed(motion, reach, float(t)) for t in ts)


def config_motion(motion, rest_points) -> "RigidMotion":
    """The RigidMotion of a config ``motion`` (pipeline.scene.Motion) of a wall whose rest pose has the points
    ``rest_points``: about its pivot, by default the centre of their bounding box."""
    pts = np.asarray(rest_points, np.float64)
    pivot = 0.5 * (pts.min(axis=0) + pts.max(axis=0)) if motion.pivot is None else motion.pivot
    return RigidMotion.from_keyframes(motion.keyframes, pivot)


def wall_speed(motion, reach: float, t: float) -> float:
    """The fastest a wall point within ``reach`` of the pivot goes at t: |v| + |omega| reach (``motion``:
    anything with RigidMotion's ``velocity(t)``)."""
    v, w = motion.velocity(t)
    return float(np.linalg.norm(v)) + float(np.linalg.norm(w)) * reach
