"""Axis and line errors for evaluating joint estimates against ground truth (pure core)."""

from __future__ import annotations

import numpy as np

__all__ = ['axis_angle_deg', 'point_line_distance', 'line_distance_over_segment']


def axis_angle_deg(axis: np.ndarray, axis_true: np.ndarray) -> float:
    """
    Angle [deg] between two joint axes, in [0, 90].

    An axis has no sign (a revolute joint about ``-u`` is the same joint), so the angle is that
    of the lines. Both are (3,) unit vectors in the same frame.
    """
    c = abs(float(np.asarray(axis, dtype=float) @ np.asarray(axis_true, dtype=float)))
    return float(np.degrees(np.arccos(min(c, 1.0))))


def point_line_distance(point: np.ndarray, line_point: np.ndarray,
                        line_direction: np.ndarray) -> float:
    """Distance [m] of ``point`` (3,) from the line through ``line_point`` along unit ``u``."""
    d = np.asarray(point, dtype=float) - np.asarray(line_point, dtype=float)
    u = np.asarray(line_direction, dtype=float)
    return float(np.linalg.norm(d - u * (d @ u)))


def line_distance_over_segment(point_true: np.ndarray, axis_true: np.ndarray,
                               anchor: np.ndarray, point: np.ndarray, axis: np.ndarray,
                               half_length: float = 0.1) -> float:
    """
    Largest distance [m] of an estimated axis line from the true one over a segment of it.

    Two lines that are nearly parallel have their closest points anywhere: the error that
    matters is where the joint is used. The segment is the true line's ``+- half_length`` [m]
    about the foot of ``anchor`` on it (e.g. the mean position of the moving link); the result
    is the larger distance of the segment's two ends from the estimated line. All (3,) in the
    same frame, axes unit vectors.
    """
    c = np.asarray(point_true, dtype=float)
    u = np.asarray(axis_true, dtype=float)
    foot = c + u * ((np.asarray(anchor, dtype=float) - c) @ u)
    return max(point_line_distance(foot + s * u, point, axis) for s in (-half_length, half_length))
