"""Bring-up of the stereo_manip graph: the demo pipeline runner and the launch file."""
