"""Dense-mesh animation by per-facet affine transfer from the sparse model."""
