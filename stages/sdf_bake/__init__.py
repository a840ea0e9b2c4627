"""sdf_bake: the walls' narrow-band signed distance field (stages/common/sdf.py) for simulate and wall_snap."""
