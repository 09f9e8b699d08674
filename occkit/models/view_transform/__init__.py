"""View transforms: image features -> BEV (projection-and-sampling, LSS)."""
