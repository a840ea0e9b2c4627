"""Writes open_bowl.obj: an open hemispherical bowl of radius 1 (a single surface, no thickness) with
a flat rim 0.12 wide, Z up, its bottom at z = 0; 48 segments around, 12 rings. Made for this project
(CC0). Run: python configs/assets/make_open_bowl.py"""
from pathlib import Path

import numpy as np

SEGMENTS, RINGS, LIP = 48, 12, 0.12

phi = np.linspace(0, 2 * np.pi, SEGMENTS, endpoint=False)
theta = np.linspace(0, np.pi / 2, RINGS + 1)[1:]  # from the bottom pole up to the rim
rings = [np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), 1 - np.cos(t) + 0 * phi], 1) for t in theta]
rings.append(rings[-1] * [1 + LIP, 1 + LIP, 1])  # the flat rim, outwards at the rim's height
v = np.concatenate([[[0.0, 0.0, 0.0]]] + rings)
faces = [(0, 1 + (j + 1) % SEGMENTS, 1 + j) for j in range(SEGMENTS)]
for r in range(len(rings) - 1):
    a, b = 1 + r * SEGMENTS, 1 + (r + 1) * SEGMENTS
    for j in range(SEGMENTS):
        k = (j + 1) % SEGMENTS
        faces += [(a + j, a + k, b + k), (a + j, b + k, b + j)]
lines = ["# open hemispherical bowl, radius 1, rim 0.12 wide (configs/assets/make_open_bowl.py)"]
lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
Path(__file__).with_name("open_bowl.obj").write_text("\n".join(lines) + "\n")

# The same bowl as a studio would hand it over (configs/open_bowl.yaml): a USD set in centimetres,
# Y up, quads around the rings, under two transformed ancestors (25 cm radius, its bottom 3 cm up).
from pxr import Gf, Usd, UsdGeom  # noqa: E402

stage = Usd.Stage.CreateNew(str(Path(__file__).with_name("open_bowl_set.usda")))
UsdGeom.SetStageMetersPerUnit(stage, 0.01)
UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
world = UsdGeom.Xform.Define(stage, "/World")
world.AddTranslateOp().Set(Gf.Vec3d(0, 3, 0))
props = UsdGeom.Xform.Define(stage, "/World/Props")
props.AddScaleOp().Set(Gf.Vec3f(25, 25, 25))
mesh = UsdGeom.Mesh.Define(stage, "/World/Props/Bowl")
mesh.CreatePointsAttr([Gf.Vec3f(float(x), float(z), float(-y)) for x, y, z in v])  # Z up -> Y up
counts, indices = [3] * SEGMENTS, [i for j in range(SEGMENTS) for i in (0, 1 + (j + 1) % SEGMENTS, 1 + j)]
for r in range(len(rings) - 1):
    a, b = 1 + r * SEGMENTS, 1 + (r + 1) * SEGMENTS
    for j in range(SEGMENTS):
        k = (j + 1) % SEGMENTS
        counts.append(4)
        indices += [a + j, a + k, b + k, b + j]
mesh.CreateFaceVertexCountsAttr(counts)
mesh.CreateFaceVertexIndicesAttr(indices)
stage.SetDefaultPrim(world.GetPrim())
stage.GetRootLayer().Save()
