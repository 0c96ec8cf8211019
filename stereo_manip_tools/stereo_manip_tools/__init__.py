"""
Shared tools for stereo_manip.

message/array conversions, pose math, mesh I/O, stamp synchroniser, rosbag2 record/replay, test
harness.
"""
