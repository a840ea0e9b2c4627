"""The project's own stage implementations, one folder per stage kind, one module per implementation.
They are registered through the ``pipeline.stages`` entry-point group (pyproject.toml), like any
third-party stage; ``common/`` holds the numerics and artifact formats that several stages share."""
