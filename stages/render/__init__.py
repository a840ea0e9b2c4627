"""render stage: offscreen frames (pyvista)."""
