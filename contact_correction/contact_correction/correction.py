"""
One-call vision error correction of a moving object's pose with contact relations.

:func:`correct_pose` chains Section 3's steps -- contact relation (detected or given), the
non-linear correction, then (optionally) the optimal linear correction -- and guards them: bad
input (non-rotation matrices, NaN, no contact, a relation that cannot be met, a pose far from
the relation, remaining penetration) never raises; the observed pose is passed through
unchanged with ``corrected=False`` and a ``status`` naming the reason.

Poses are 4x4 matrices in any common frame (e.g. the left camera's optical frame); all
directions, contact points and normals in the result are in the fixed object's model frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Dict, List, Optional, Sequence

import numpy as np
from stereo_manip_tools.transforms import check_transform, rotation_log

from .contact_relation import (
    ContactGeometry, ContactPair, detect_contact_relation, evaluate_contacts,
    off_element_distance, penetration_depth, relative_pose)
from .nonlinear_correction import correct_nonlinear, RESIDUAL_TOLERANCE
from .optimal_correction import (
    constraint_directions, constraint_matrix, ConstraintDirections, correct_optimal,
    optimal_translation, reference_translation, scaled_singular_values)
from .polyhedron import Polyhedron

__all__ = ['CorrectionResult', 'correct_pose']


@dataclass
class CorrectionResult:
    """
    Outcome of :func:`correct_pose` for one frame.

    :ivar T_moving: corrected pose of the moving object (4x4, input frame); the observed pose,
        unchanged, when ``corrected`` is False.
    :ivar T_nonlinear: pose after the non-linear step (None if it did not run).
    :ivar corrected: True when a correction was applied.
    :ivar status: method and rank case, or why the pose was passed through.
    :ivar method: 'optimal/<rank rule>', 'nonlinear' or 'passthrough'.
    :ivar pairs: the contact relation used.
    :ivar directions: constrained / free directions (fixed frame), None without contacts.
    :ivar geometry: contact distances, points, normals at the returned pose (fixed frame).
    :ivar penetration_before: penetration depth at the observed pose [m] (nan if unchecked).
    :ivar penetration_after: penetration depth at the returned pose [m] (nan if unchecked).
    :ivar max_residual: largest |contact distance| at the returned pose [m].
    :ivar translation_change: change of the moving origin in the fixed frame [m], (3,).
    :ivar rotation_change: rotation vector of the orientation change, fixed frame [rad], (3,).
    :ivar elapsed: wall time of the correction [s].
    :ivar relation_source: where the relation came from: 'given', 'detected' (one tolerance)
        or 'recognised' (model selection + temporal model, :mod:`.recognition`), with
        ', fallback k' when the k-th alternative relation had to be used.
    :ivar reference_point: (3,) the point of the moving object [m, moving frame] whose
        observed position the correction kept along the free directions (the optimal step's
        ``reference_point``); None: the moving origin (every non-linear-only result).
    :ivar guarded: True when the correction-size guard refused a correction far beyond the
        stated pose noise (:attr:`~contact_correction.recognition.RecognitionOptions.\
max_correction_sigma`) and a relation with fewer constraints, the non-penetration only
        correction or the observation was used instead (the status says which).
    """

    T_moving: np.ndarray
    T_nonlinear: Optional[np.ndarray] = None
    corrected: bool = False
    status: str = ''
    method: str = 'passthrough'
    pairs: List[ContactPair] = field(default_factory=list)
    directions: Optional[ConstraintDirections] = None
    geometry: Optional[ContactGeometry] = None
    penetration_before: float = float('nan')
    penetration_after: float = float('nan')
    max_residual: float = float('nan')
    translation_change: np.ndarray = field(default_factory=lambda: np.zeros(3))
    reference_point: Optional[np.ndarray] = None
    rotation_change: np.ndarray = field(default_factory=lambda: np.zeros(3))
    elapsed: float = 0.0
    relation_source: str = ''
    guarded: bool = False

    @property
    def rotation_rank(self) -> int:
        """Rank of Eq. 3 (0 without contacts)."""
        return self.directions.rotation_rank if self.directions is not None else 0

    @property
    def constraint_rank(self) -> int:
        """Rank of Eq. 2 (0 without contacts)."""
        return self.directions.constraint_rank if self.directions is not None else 0


def _near_degenerate(A: np.ndarray, length_scale: float, lo: float = 1e-9,
                     hi: float = 1e-4, singular_values: Optional[np.ndarray] = None) -> bool:
    """
    Tell whether the pose sits at (or next to) a degenerate configuration of the relation.

    True when Eq. 2's matrix has a singular value that is neither clearly zero nor clearly
    non-zero (relative to the largest, rotation columns divided by ``length_scale``): the
    pose sits at (or next to) a degenerate configuration of the relation.

    :param singular_values: ``scaled_singular_values(A, length_scale)`` when known already.
    """
    if len(A) == 0:
        return False
    s = scaled_singular_values(A, length_scale) if singular_values is None \
        else singular_values
    r = s / max(s[0], 1e-300)
    return bool(np.any((r > lo) & (r < hi)))


#: poses that passed check_transform lately (their bytes): a track's fixed pose, and the
#: observation tried again by the fallbacks of one frame, are checked once
_VALID_POSES: Dict[bytes, None] = {}


def _checked_transform(T: np.ndarray, name: str) -> np.ndarray:
    """Return ``check_transform(T, name)``, remembering the last few valid poses."""
    A = np.asarray(T, dtype=float)
    key = A.tobytes() if A.shape == (4, 4) else None
    if key is not None and key in _VALID_POSES:
        return A
    A = check_transform(T, name)
    if key is not None:
        if len(_VALID_POSES) >= 8:
            _VALID_POSES.clear()
        _VALID_POSES[key] = None
    return A


def correct_pose(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                 T_fixed: np.ndarray, pairs: Optional[Sequence[ContactPair]] = None, *,
                 optimal: bool = True, tolerance: float = 2e-3,
                 penetration_tolerance: Optional[float] = None,
                 angle_tolerance: float = 0.1, max_translation: float = 0.02,
                 max_rotation: float = 0.35, residual_tolerance: float = RESIDUAL_TOLERANCE,
                 check_penetration: bool = True, penetration_spacing: float = 0.005,
                 element_margin: float = 1e-6,
                 rank1_method: str = 'auto', prune_off_element: bool = False,
                 penetration_before: Optional[float] = None,
                 reference_point: Optional[np.ndarray] = None,
                 nonlinear_pivot: Optional[np.ndarray] = None,
                 nonlinear_length_scale: Optional[float] = None) -> CorrectionResult:
    """
    Correct the observed pose of the moving object with the contact relation.

    :param moving: moving object's polyhedron.
    :param fixed: fixed object's polyhedron.
    :param T_moving: observed pose of the moving object (4x4).
    :param T_fixed: pose of the fixed object in the same frame (4x4).
    :param pairs: the contact relation; None = detect it at the observed pose.
    :param optimal: also apply the optimal linear correction (Eqs. 2-9).
    :param tolerance: contact detection distance [m].
    :param penetration_tolerance: deepest interpenetration counted as contact when detecting
        [m] (default ``tolerance``).
    :param angle_tolerance: detection angle slack [rad].
    :param max_translation: largest accepted change of the moving origin [m]; a larger one
        means the pose is far from the relation: passed through.
    :param max_rotation: largest accepted orientation change [rad].
    :param residual_tolerance: largest accepted contact residual after correction [m]; the
        non-linear step converges to it too (one tolerance, :data:`RESIDUAL_TOLERANCE`).
    :param check_penetration: measure penetration before and after (costs time).
    :param penetration_spacing: edge sampling step of the penetration test [m].
    :param rank1_method: see :func:`correct_optimal`.
    :param element_margin: largest accepted distance [m] of a corrected contact point outside
        its bounded elements (the relation must be realised, not only its planes).
    :param prune_off_element: drop pairs whose corrected contact point lies outside its
        elements when the rest of the relation has the same constraint rank (e.g. a vertex of
        a face-face contact beyond the overlap: its plane is the face's plane), instead of
        refusing the correction.
    :param penetration_before: the observation's penetration depth [m] when the caller has
        measured it already (same ``penetration_spacing``); None: measured here.
    :param reference_point: (3,) the point of the moving object [m, moving model frame] that
        the optimal correction's translation rule keeps where it was observed along every
        direction the relation leaves free (:func:`~contact_correction.optimal_correction.
        reference_translation`); None: the moving origin (the chapter). A non-linear-only
        result (``optimal`` False, or the optimal step refused) keeps the free coordinates of
        ``nonlinear_pivot`` (the origin's without one). The moving polyhedron's ``centroid``
        makes the correction independent of where the model's origin is: on the demo's peg
        (origin at its bottom face) sliding on the block, whose localised pose tilts about a
        point 60-90 mm up, holding the origin moved the whole peg by the tilt's lever arm
        (median ADD above the localised one in 4 of 7 runs, one tie, even with the true
        relation given); the centroid brought every run's median, p95, max and mean below.
    :param nonlinear_pivot: (3,) the point of the moving object [m, moving model frame] the
        non-linear step's metric turns about (:func:`~contact_correction.
        nonlinear_correction.correct_nonlinear`'s ``pivot``); a non-linear-only result then
        keeps this point's coordinates along the free directions, and records it as its
        ``reference_point``. None: the fixed frame's origin, and the moving origin's free
        coordinates kept (the chapter's step).
    :param nonlinear_length_scale: the non-linear step's ``L`` [m] (default: a quarter of the
        moving object's bounding-box diagonal); ``sigma_translation / sigma_rotation`` with
        ``nonlinear_pivot`` the point the pose errors turn about makes a non-linear-only result
        the feasible pose nearest the observation in stated-noise units.
    """
    t0 = time.perf_counter()
    raw = np.array(T_moving, dtype=float, copy=True) if np.size(T_moving) == 16 \
        else np.asarray(T_moving, dtype=float)

    def passthrough(status: str, **kw) -> CorrectionResult:
        res = CorrectionResult(T_moving=raw, corrected=False, status=status, **kw)
        if res.pairs:
            try:    # report the relation's distances at the observed (returned) pose
                res.geometry = evaluate_contacts(moving, fixed, relative_pose(raw, T_fixed),
                                                 res.pairs)
                res.max_residual = float(np.max(np.abs(res.geometry.distances)))
            except (ValueError, np.linalg.LinAlgError):
                pass
        res.elapsed = time.perf_counter() - t0
        return res

    try:
        Tm = _checked_transform(T_moving, 'moving pose')
        Tf = _checked_transform(T_fixed, 'fixed pose')
    except ValueError as exc:
        return passthrough(f'invalid input: {exc}')
    T_rel_E = relative_pose(Tm, Tf)
    if pairs is None:
        pairs = detect_contact_relation(moving, fixed, Tm, Tf, tolerance,
                                        penetration_tolerance, angle_tolerance)
    pairs = list(pairs)
    if not check_penetration:
        pen_before = float('nan')
    elif penetration_before is not None:
        pen_before = float(penetration_before)
    else:
        pen_before = penetration_depth(moving, fixed, Tm, Tf, penetration_spacing)
    if not pairs:
        return passthrough('no contact: no element pair within tolerance '
                           f'{tolerance:.3g} m; pose passed through',
                           penetration_before=pen_before)
    L = max(moving.size, 1e-6)
    # singular values of each Eq. 2 matrix met below, computed once (the degeneracy test and
    # the constraint rank use the same ones); keyed by identity, the matrix kept alive
    svd_memo: dict = {}

    def sv(A: np.ndarray) -> np.ndarray:
        e = svd_memo.get(id(A))
        if e is None or e[0] is not A:
            e = svd_memo[id(A)] = (A, scaled_singular_values(A, L) if len(A) else None)
        return e[1]

    def degenerate(A: np.ndarray) -> bool:
        return _near_degenerate(A, L, singular_values=sv(A))

    def directions(A: np.ndarray) -> ConstraintDirections:
        return constraint_directions(A, L, singular_values=sv(A))

    def keep_free_translation(T_rel: np.ndarray) -> np.ndarray:
        # the non-linear step's minimum-norm steps mix rotation and translation, so its
        # result may move along a translation the relation leaves free (a T-peg near the end
        # of its slot, a peg pulled out of a hole: 0.2-0.7 mm on the tracks benchmark); with
        # its orientation kept the relation is linear in the translation, and the solution
        # nearest the observation (Eq. 2's translation rule) keeps every free component
        # (with a pivot, the pivot's free coordinates are kept, not the origin's)
        t, res, _ = optimal_translation(moving, fixed, T_rel[:3, :3],
                                        reference_translation(T_rel_E, T_rel[:3, :3], pivot),
                                        pairs, free_directions=False)
        if res > residual_tolerance:
            return T_rel
        out = T_rel.copy()
        out[:3, 3] = t
        return out

    def solve(length_scale: Optional[float], schedule: tuple):
        nl = correct_nonlinear(moving, fixed, T_rel_E, pairs, length_scale=length_scale,
                               anchor_schedule=schedule,
                               residual_tolerance=residual_tolerance, pivot=pivot)
        if not nl.converged or nl.max_residual > residual_tolerance:
            return nl, None, '', '', None
        nl.T_rel = keep_free_translation(nl.T_rel)
        T_rel, method, status = nl.T_rel, 'nonlinear', 'non-linear correction'
        if optimal:
            opt = correct_optimal(moving, fixed, T_rel_E, nl.T_rel, pairs, rank1_method,
                                  residual_tolerance=residual_tolerance,
                                  reference_point=reference_point)
            if opt.max_residual <= residual_tolerance:
                T_rel = opt.T_rel
                method = f'optimal/{opt.method}'
                status = (f'optimal correction ({opt.method}, rotation rank '
                          f'{opt.directions.rotation_rank})')
            else:
                status = (f'optimal correction ({opt.method}) left residual '
                          f'{opt.max_residual:.3g} m; non-linear result kept')
        A, geom = constraint_matrix(moving, fixed, T_rel, pairs)
        return nl, T_rel, method, status, (A, geom)

    pivot = None if nonlinear_pivot is None \
        else np.asarray(nonlinear_pivot, dtype=float).reshape(3)
    step_scale = nonlinear_length_scale or max(moving.size / 4.0, 1e-6)
    try:
        nl, T_rel, method, status, cm = solve(step_scale, (3e-2, 3e-3))
        if cm is not None and degenerate(cm[0]):
            # the non-linear step reached a degenerate configuration of the relation (e.g.
            # a peg just inside a hole pulled up to the rim, where it may tilt): retry with
            # rotations cheaper and a stronger pull towards the observation
            nl2, T2, m2, s2, cm2 = solve(step_scale / 4.0, (1e-1, 3e-2, 3e-3, 3e-4))
            if cm2 is not None:
                nl, T_rel, method, status, cm = nl2, T2, m2, s2 + ' (retried)', cm2
    except ValueError as exc:
        return passthrough(f'invalid contact relation: {exc}', pairs=pairs,
                           penetration_before=pen_before)
    if cm is None:
        return passthrough(f'relation not satisfiable near the observed pose (residual '
                           f'{nl.max_residual:.3g} m); pose passed through', pairs=pairs,
                           penetration_before=pen_before)
    A, geom = cm
    dirs = directions(A)
    T_nl = Tf @ nl.T_rel
    if degenerate(A) and method != 'nonlinear':
        # fall back to the non-linear result when it is not degenerate itself
        A_nl, geom_nl = constraint_matrix(moving, fixed, nl.T_rel, pairs)
        if not degenerate(A_nl):
            T_rel, method, A, geom = nl.T_rel, 'nonlinear', A_nl, geom_nl
            status = ('non-linear correction (the optimal one reached a degenerate '
                      'configuration of the relation)')
            dirs = directions(A)
    if degenerate(A):
        return passthrough(
            f'{method} correction reached a degenerate configuration of the relation (Eq. 2 '
            'nearly loses rank: e.g. pulled to the rim of a hole); pose passed through',
            pairs=pairs, directions=dirs, penetration_before=pen_before, T_nonlinear=T_nl)
    dt = T_rel[:3, 3] - T_rel_E[:3, 3]
    dr = rotation_log(T_rel[:3, :3] @ T_rel_E[:3, :3].T)
    T_out = Tf @ T_rel
    if np.linalg.norm(dt) > max_translation or np.linalg.norm(dr) > max_rotation:
        return passthrough(
            f'pose far from the contact relation: correction {np.linalg.norm(dt):.3g} m / '
            f'{np.linalg.norm(dr):.3g} rad exceeds {max_translation:.3g} m / '
            f'{max_rotation:.3g} rad; pose passed through', pairs=pairs, directions=dirs,
            penetration_before=pen_before, T_nonlinear=T_nl)
    off = off_element_distance(moving, fixed, T_rel, pairs)
    if prune_off_element and off.max(initial=0.0) > element_margin:
        keep = off <= element_margin
        if np.any(keep):
            A_keep = A[keep]
            dk = directions(A_keep)
            if dk.constraint_rank == dirs.constraint_rank \
                    and dk.rotation_rank == dirs.rotation_rank:
                pairs = [p for p, k in zip(pairs, keep) if k]
                geom = ContactGeometry(geom.distances[keep], geom.points[keep],
                                       geom.normals[keep])
                A, dirs, off = A_keep, dk, off[keep]
    if off.max(initial=0.0) > element_margin:
        k = int(np.argmax(off))
        return passthrough(
            f'{method} correction meets the contact planes but contact {k} ({pairs[k]}) lies '
            f'{off[k]:.3g} m outside its elements (e.g. a free coordinate kept as observed '
            'is outside the range where the relation exists); pose passed through',
            pairs=pairs, directions=dirs, penetration_before=pen_before, T_nonlinear=T_nl)
    pen_after = (penetration_depth(moving, fixed, T_out, Tf, penetration_spacing)
                 if check_penetration else float('nan'))
    if check_penetration and pen_after > max(residual_tolerance, 1e-6) \
            and method != 'nonlinear':
        # the optimal step's rotation may dip an element outside the relation into the other
        # object; the non-linear result (any feasible pose near the observation) may not
        pen_nl = penetration_depth(moving, fixed, T_nl, Tf, penetration_spacing)
        if pen_nl <= max(residual_tolerance, 1e-6):
            A_nl, geom_nl = constraint_matrix(moving, fixed, nl.T_rel, pairs)
            off_nl = off_element_distance(moving, fixed, nl.T_rel, pairs)
            if not degenerate(A_nl) and off_nl.max(initial=0.0) <= element_margin:
                T_rel, T_out, A, geom, pen_after = nl.T_rel, T_nl, A_nl, geom_nl, pen_nl
                dirs = directions(A)
                dt = T_rel[:3, 3] - T_rel_E[:3, 3]
                dr = rotation_log(T_rel[:3, :3] @ T_rel_E[:3, :3].T)
                status = (f'non-linear correction ({method} left penetration '
                          f'{pen_after:.3g} m)')
                method = 'nonlinear'
    if check_penetration and pen_after > max(residual_tolerance, 1e-6):
        return passthrough(
            f'penetration {pen_after:.3g} m remains after {method} correction (relation '
            'incomplete?); pose passed through', pairs=pairs, directions=dirs,
            penetration_before=pen_before, penetration_after=pen_after, T_nonlinear=T_nl)
    res = CorrectionResult(
        T_moving=T_out, T_nonlinear=T_nl, corrected=True, status=status, method=method,
        pairs=pairs, directions=dirs, geometry=geom, penetration_before=pen_before,
        penetration_after=pen_after, max_residual=float(np.max(np.abs(geom.distances))),
        translation_change=dt, rotation_change=dr,
        reference_point=(None if pivot is None else pivot.copy()) if method == 'nonlinear'
        else None if reference_point is None
        else np.asarray(reference_point, dtype=float).reshape(3).copy())
    res.elapsed = time.perf_counter() - t0
    return res
