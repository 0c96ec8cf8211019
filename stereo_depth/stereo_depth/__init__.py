"""
Stereo pairs to disparity, depth and point clouds, and the synthetic stereo camera.

Stereo pairs to disparity, depth and point clouds (matching cost, aggregation, optimisation of
Eq. 1, refinement) and the synthetic stereo camera.
"""
