"""Moving rigid walls (issue 18) outside the solver: the RigidMotion model, the config, mesh_import
(config keyframes and USD time samples), sdf_bake (bodies), wall_snap, render and export."""
from __future__ import annotations

import json

import numpy as np
import pytest

from stages.common.motion import RigidMotion, matrix_to_quat, quat_to_matrix
from stages.common.placement import rotation_xyz

KEYS = [{"time": 0.0, "translate": [0, 0, 0], "rotate": [0, 0, 0]},
        {"time": 0.5, "translate": [0.2, 0.0, 0.1], "rotate": [0, 0, 60]},
        {"time": 1.5, "translate": [0.2, -0.3, 0.1], "rotate": [30, 10, 60]}]
PIVOT = [0.1, 0.2, 0.3]


def _motion() -> RigidMotion:
    return RigidMotion.from_keyframes(KEYS, PIVOT)


def test_pose_at_keys_is_exact():
    m = _motion()
    for k in KEYS:
        r, t = m.pose(k["time"])
        assert np.allclose(r, rotation_xyz(k["rotate"]), atol=1e-12)
        assert np.allclose(t, k["translate"], atol=1e-12)


def test_slerp_midpoint_is_half_the_turn():
    m = _motion()
    r, t = m.pose(0.25)
    assert np.allclose(r, rotation_xyz([0, 0, 30]), atol=1e-12)
    assert np.allclose(t, [0.1, 0.0, 0.05], atol=1e-12)
    # between two general keys: the midpoint rotation is equidistant (geodesically) from both
    r0, r1 = rotation_xyz(KEYS[1]["rotate"]), rotation_xyz(KEYS[2]["rotate"])
    rm, _ = m.pose(1.0)

    def angle(a, b):
        return np.arccos(np.clip((np.trace(a.T @ b) - 1) / 2, -1, 1))

    assert angle(r0, rm) == pytest.approx(angle(rm, r1), abs=1e-12)
    assert angle(r0, rm) == pytest.approx(0.5 * angle(r0, r1), abs=1e-12)


@pytest.mark.parametrize("t", [0.0, 0.13, 0.5, 0.77, 1.2])
def test_velocity_is_the_derivative_of_pose(t):
    m = _motion()
    eps = 1e-6
    (ra, ta), (rb, tb) = m.pose(t), m.pose(t + eps)
    v, w = m.velocity(t)
    assert np.allclose(v, (tb - ta) / eps, atol=1e-6)
    skew = (rb - ra) / eps @ ra.T  # R' R^T = [omega]x
    assert np.allclose(w, [skew[2, 1], skew[0, 2], skew[1, 0]], atol=1e-5)
    assert np.linalg.norm(w) > 0.1  # every segment turns
    # a point of the wall moves at v + omega x (x - pivot - T): the finite difference of to_world
    x = np.array([[0.4, -0.2, 0.9]])
    xa, xb = m.to_world(x, t), m.to_world(x, t + eps)
    r, tr = m.pose(t)
    assert np.allclose(v + np.cross(w, xa[0] - m.pivot - tr), (xb - xa)[0] / eps, atol=1e-5)


def test_pose_is_held_outside_the_span():
    m = _motion()
    for t, k in ((-1.0, 0), (1.5, 2), (7.0, 2)):
        r, tr = m.pose(t)
        assert np.allclose(r, rotation_xyz(KEYS[k]["rotate"]), atol=1e-12)
        assert np.allclose(tr, KEYS[k]["translate"], atol=1e-12)
        v, w = m.velocity(t)
        assert not v.any() and not w.any()
    one = RigidMotion.from_keyframes(KEYS[1:2], PIVOT)
    assert np.allclose(one.pose(3.0)[1], KEYS[1]["translate"]) and not one.velocity(0.5)[0].any()


def test_json_round_trip_and_scaled():
    m = _motion()
    back = RigidMotion.from_json(json.loads(json.dumps(m.to_json())))
    for t in (-0.5, 0.3, 0.9, 2.0):
        assert np.allclose(back.matrix(t), m.matrix(t), atol=1e-15)
    s = m.scaled(0.01)
    x = np.array([[1.0, 2.0, 3.0]])
    assert np.allclose(s.to_world(x * 0.01, 0.7), m.to_world(x, 0.7) * 0.01, atol=1e-15)
    assert np.allclose(m.to_rest(m.to_world(x, 0.7), 0.7), x, atol=1e-12)


def test_swept_bounds_cover_the_moving_box():
    m = _motion()
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.3, 0.2, 0.5])
    slo, shi = m.swept_bounds(lo, hi)
    rng = np.random.default_rng(0)
    pts = lo + rng.random((200, 3)) * (hi - lo)
    for t in np.linspace(-0.2, 1.7, 97):
        w = m.to_world(pts, t)
        assert (w >= slo - 1e-3 * 0.6).all() and (w <= shi + 1e-3 * 0.6).all()


def test_quaternion_conversions_agree():
    for deg in ([0, 0, 0], [180, 0, 0], [0, 179, 3], [-120, 45, 170]):
        r = rotation_xyz(deg)
        assert np.allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)


def test_from_matrices_rejects_a_scaling_animation():
    m = np.eye(4)
    m[:3, :3] *= 1.1
    with pytest.raises(ValueError, match="not rigid"):
        RigidMotion.from_matrices([0.0, 1.0], [np.eye(4), m], [0, 0, 0])
    good = _motion()
    back = RigidMotion.from_matrices(good.times, [good.matrix(t) for t in good.times], good.pivot)
    for t in (0.2, 0.8, 1.4):
        assert np.allclose(back.matrix(t), good.matrix(t), atol=1e-12)
