"""
Joint parameters and corrected trajectories from two links' pose tracks.

Joint parameters and corrected trajectories from two links' pose tracks (Eqs. 10-18), with
automatic joint type selection.
"""
