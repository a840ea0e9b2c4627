"""simulate stage implementations (SPH with distance-function walls; shared numerics for MPS)."""
