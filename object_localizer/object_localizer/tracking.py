"""6-DOF pose tracking over time: fine localisation from the previous pose, global re-detection
when the track is lost (pure core, no ROS)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np

from object_localizer.localization import localize, LocalizationResult, ModelTemplate

__all__ = ['TrackerSettings', 'ObjectTracker']


@dataclass
class TrackerSettings:
    """Tracker parameters (metres).

    :ivar max_distance: ICP correspondence radius [m].
    :ivar loss: M-estimator, ``tukey``/``huber``/``l2``.
    :ivar loss_scale: M-estimator scale [m].
    :ivar min_inlier_fraction: below it a fine result counts as lost and the object is searched
        globally (rough + fine); a global result below it is reported as not found.
    :ivar drop_plane: remove the dominant plane (table) before the global search.
    :ivar seed: RANSAC seed.
    :ivar max_history: poses kept in :attr:`ObjectTracker.history`.
    """

    max_distance: float = 0.01
    loss: str = 'tukey'
    loss_scale: float = 0.0015
    min_inlier_fraction: float = 0.5
    drop_plane: bool = True
    seed: int = 0
    max_history: int = 1000


@dataclass
class ObjectTracker:
    """Tracks one model through successive scene clouds."""

    model: ModelTemplate
    settings: TrackerSettings = field(default_factory=TrackerSettings)
    history: List[tuple] = field(default_factory=list)
    lost_count: int = 0
    _prior: Optional[np.ndarray] = None

    def reset(self, pose: Optional[np.ndarray] = None) -> None:
        """Forget the track; with ``pose`` (4x4 model -> sensor) start tracking from it."""
        self._prior = None if pose is None else np.asarray(pose, dtype=float).copy()

    def update(self, points: np.ndarray, stamp_ns: int) -> Optional[LocalizationResult]:
        """Localise in a new cloud (N, 3) [m]; returns None (and counts it) when not found.

        :raises ValueError: the cloud is unusable (shape, too few finite points).
        """
        s = self.settings
        result = localize(self.model, points, prior=self._prior,
                          min_inlier_fraction=s.min_inlier_fraction, seed=s.seed,
                          max_distance=s.max_distance, loss=s.loss, loss_scale=s.loss_scale,
                          drop_plane=s.drop_plane)
        if result.inlier_fraction < s.min_inlier_fraction:
            self.lost_count += 1
            self._prior = None
            return None
        self._prior = result.pose
        self.history.append((int(stamp_ns), result.pose))
        del self.history[:-s.max_history]
        return result
