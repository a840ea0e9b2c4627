"""surface_extract implementations: a triangle mesh of the fluid surface per frame."""
