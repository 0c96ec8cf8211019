"""Known 3D models localised in point clouds: descriptors + RANSAC, then ICP with an M-estimator;
6-DOF pose tracking.
"""
