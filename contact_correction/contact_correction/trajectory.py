"""Trajectory mode: correct a whole observed track of the moving object (Section 3, Fig. 9).

Each frame is corrected independently with its own contact relation (detected at the observed
pose, or given), and reported with the relation, the rank, the constrained and free directions
and the correction applied (:class:`contact_correction.correction.CorrectionResult`).
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from .contact_relation import ContactPair
from .correction import CorrectionResult, correct_pose
from .polyhedron import Polyhedron

__all__ = ['correct_trajectory', 'trajectory_components']


def correct_trajectory(moving: Polyhedron, fixed: Polyhedron, moving_poses: np.ndarray,
                       fixed_poses: np.ndarray,
                       relations: Optional[Sequence[Optional[Sequence[ContactPair]]]] = None,
                       **kwargs: Any) -> List[CorrectionResult]:
    """Correct every frame of an observed trajectory.

    :param moving_poses: observed moving-object poses, shape (N, 4, 4).
    :param fixed_poses: fixed-object poses, shape (N, 4, 4), or one (4, 4) pose for all frames.
    :param relations: per-frame contact relations (None entries, or None = detect each frame).
    :param kwargs: passed to :func:`contact_correction.correction.correct_pose`
        (``optimal``, ``tolerance``, ...).
    :raises ValueError: on mismatched lengths (per-frame problems are reported, not raised).
    """
    Tm = np.asarray(moving_poses, dtype=float).reshape(-1, 4, 4)
    Tf = np.asarray(fixed_poses, dtype=float)
    if Tf.shape == (4, 4):
        Tf = np.broadcast_to(Tf, Tm.shape)
    Tf = Tf.reshape(-1, 4, 4)
    if len(Tf) != len(Tm):
        raise ValueError(f'{len(Tm)} moving poses but {len(Tf)} fixed poses '
                         '(give one per frame, or a single one)')
    if relations is not None and len(relations) != len(Tm):
        raise ValueError(f'{len(relations)} relations for {len(Tm)} frames')
    out = []
    for k in range(len(Tm)):
        rel = relations[k] if relations is not None else None
        out.append(correct_pose(moving, fixed, Tm[k], Tf[k], rel, **kwargs))
    return out


def trajectory_components(results: Sequence[CorrectionResult], moving_poses: np.ndarray,
                          fixed_poses: np.ndarray, axes: Optional[np.ndarray] = None
                          ) -> Dict[str, np.ndarray]:
    """Positions of the observed and corrected origins in the fixed frame, projected on axes.

    :param axes: (3, 3) rows = projection axes in the fixed frame; default: the constrained
        and free translation directions of the first corrected frame with contacts (the Fig. 9
        decomposition), completed to an orthonormal basis.
    :returns: dict with 'observed' and 'corrected' (output pose; the observed one for frames
        passed through) (N, 3) components, 'axes' (3, 3) and 'labels' (3,) ('constrained' /
        'free' per axis, or 'x', 'y', 'z').
    """
    Tm = np.asarray(moving_poses, dtype=float).reshape(-1, 4, 4)
    Tf = np.asarray(fixed_poses, dtype=float)
    if Tf.shape == (4, 4):
        Tf = np.broadcast_to(Tf, Tm.shape)
    labels = np.array(['x', 'y', 'z'])
    if axes is None:
        axes = np.eye(3)
        for r in results:
            if r.corrected and r.directions is not None:
                d = r.directions
                axes = np.vstack([d.constrained_translation, d.free_translation])
                labels = np.array(['constrained'] * len(d.constrained_translation)
                                  + ['free'] * len(d.free_translation))
                break
    obs = np.array([np.linalg.solve(Tf[k], Tm[k])[:3, 3] for k in range(len(Tm))])
    cor = np.array([np.linalg.solve(Tf[k], np.asarray(r.T_moving, dtype=float).reshape(4, 4))
                    [:3, 3] for k, r in enumerate(results)])
    return {'observed': obs @ axes.T, 'corrected': cor @ axes.T, 'axes': axes,
            'labels': labels}
