"""Input files other than a capture: meshes from disk (e.g. the reference of eval.surface)."""
