"""
Known 3D models localised in point clouds.

Descriptors + RANSAC, then ICP with an M-estimator; 6-DOF pose tracking.
"""
