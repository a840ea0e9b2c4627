"""wall_snap implementations: move surface vertices near a wall onto it."""
