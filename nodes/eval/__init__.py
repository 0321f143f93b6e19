"""Eval: quality metrics (silhouette agreement, surface distances)."""
