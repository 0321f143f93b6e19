"""Mesh: marching cubes, refinement onto the exact visual hull, relaxation that keeps the silhouettes."""
