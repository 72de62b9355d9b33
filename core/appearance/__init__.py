"""Appearance models: descriptor maps sampled from images, la/tex models and their training."""
