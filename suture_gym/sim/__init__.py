"""Physics: meshes, models, constraint kernels and the XPBD solver. Knows nothing of rewards."""
