"""Optimisation: initialisation from LiDAR, adaptive density control, the training stages."""
