"""Temporal structuring: classify a mesh sequence (seed chapter, Table 8.1) and track keyframe meshes through
per-frame reconstructions into a dynamic mesh (constant connectivity per segment), with its exports."""
