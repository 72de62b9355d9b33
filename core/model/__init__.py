"""The speaker model: the linear articulatory face model, its building by guided PCA, the camera."""
