"""Texturing: per-face view selection, seam levelling, atlas, baking (kernels/texture.cl)."""
