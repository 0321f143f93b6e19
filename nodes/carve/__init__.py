"""Photo-consistency carving: voxel colouring and space carving of the visual hull (OpenCL)."""
