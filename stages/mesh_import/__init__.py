"""mesh_import: wall models (built-in shapes, mesh files, OpenUSD prims) to one cleaned world-space WallMesh.

Orientation convention of the output (walls.npz): every triangle's normal (counter-clockwise winding)
points into the fluid. A solid obstacle (fluid="outside") faces outwards, a container (fluid="inside")
faces inwards. A shell (fluid "both", an open or single-sided surface thickened on both sides) keeps
the winding trimesh made consistent. The SDF sign does not depend on it (sdf_bake uses ray voting and the per-wall fluid
side from walls.json); renderers and wall_snap may.
"""
