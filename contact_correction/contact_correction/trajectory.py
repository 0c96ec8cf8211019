"""
Trajectory mode: correct an observed track of the moving object (Section 3, Fig. 9).

Two ways to get each frame's relation:

* ``recognition=None`` (the per-frame detection of the first version): the relation is
  detected at each observed pose with one distance tolerance (or given per frame);
* ``recognition=RecognitionOptions(...)``: the relation is *recognised*
  (:mod:`contact_correction.recognition`: model selection against the stated pose noise and a
  temporal model over the track). :class:`ContactCorrector` does it online, frame by frame
  (the node); :func:`correct_trajectory` back-tracks the whole track (Viterbi) offline.

When the correction with the chosen relation is refused (not satisfiable, degenerate, contact
points off their elements, penetration left, correction over the limits) the next best
relations of the frame are tried (fewer or other constraints), and a penetrating observation
with no usable relation is pushed out by the non-linear step on its penetrating pairs, so that
penetration is not passed through. A correction far beyond the stated pose noise (the
correction-size guard, ``RecognitionOptions.max_correction_sigma``) is not applied blindly:
the relations nested in the chosen one, then the non-penetration only correction, are tried
and the result is flagged (``CorrectionResult.guarded``).
"""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
from stereo_manip_tools.transforms import rotation_log

from .contact_relation import (
    ContactGeometry, ContactPair, detect_contact_relation, evaluate_contacts, FACE,
    penetration_depth, relative_pose, VERTEX)
from .correction import correct_pose, CorrectionResult
from .nonlinear_correction import apply_screw, constraint_rows
from .optimal_correction import constraint_directions, constraint_matrix, held_point
from .polyhedron import Polyhedron
from .recognition import (
    FrameCandidates, Hypothesis, recognise_track, RecognitionOptions, RelationRecognizer,
    RelationTracker)

__all__ = ['correct_trajectory', 'trajectory_components', 'ContactCorrector',
           'correct_recognised', 'guard_limits', 'push_out_inequalities']

#: alternative relations tried when the chosen one is refused
MAX_FALLBACKS = 3

#: [m] largest accepted change along a direction the enforced relation leaves free
FREE_TOLERANCE = 1e-7

#: [m] faces this close to a vertex's nearest exit count as its exits (push-outs)
EXIT_MARGIN = 1e-4

#: [m] probe step into a face-face contact at the corrected pose: a real contact penetrates
#: (depth about the step), one whose faces meet only along a boundary does not
CONTACT_PROBE = 1e-4


def correct_recognised(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                       T_fixed: np.ndarray, chosen: Hypothesis, frame: FrameCandidates,
                       guard: Optional[np.ndarray] = None,
                       recognition_margin: Optional[float] = None,
                       guard_limits: Optional[Tuple[float, float]] = None,
                       noise: Optional[Tuple[float, float]] = None,
                       **kwargs: Any) -> CorrectionResult:
    """
    Correct one frame with a recognised relation, with fallbacks.

    Every path (the chosen relation, a nested one under the guard, a fallback relation, a
    push-out) ends with one check against the free directions of the relation the result
    enforces (:func:`_honour_free_directions`): a change along them above
    :data:`FREE_TOLERANCE` is undone, or the correction refused (the observation passed
    through) or, when the observation penetrates and no pose without that change is found,
    flagged (``guarded``) with the size in its status; never silent.

    Parameters as :func:`_correct_recognised_paths`.
    """
    r = _correct_recognised_paths(moving, fixed, T_moving, T_fixed, chosen, frame, guard,
                                  recognition_margin, guard_limits, noise, **kwargs)
    return _honour_free_directions(moving, fixed, T_moving, T_fixed, frame, r, **kwargs)


def _honour_free_directions(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                            T_fixed: np.ndarray, frame: FrameCandidates,
                            r: CorrectionResult, **kwargs: Any) -> CorrectionResult:
    """
    Undo (or refuse, or flag) a change along the free directions of ``r``'s own relation.

    The free translations of ``r.pairs`` as the recognition sees them
    (:func:`_recognised_free_translation`, at the observed pose, fixed frame). A change of the
    moving origin (or of ``r.reference_point``, :func:`~contact_correction.
    optimal_correction.held_point`) along them above :data:`FREE_TOLERANCE` is removed when
    the pose keeps the relation's contacts (within the residual tolerance) and stays out of
    penetration there; else a non-penetrating observation is passed through (``guarded``,
    status says why); else (the observation penetrates, the correction is the only one
    removing it) the correction is kept and flagged ``guarded`` with the size of the change
    in its status.
    """
    if not r.corrected or not r.pairs:
        return r
    T_o, T_c = relative_pose(T_moving, T_fixed), relative_pose(r.T_moving, T_fixed)
    F = _recognised_free_translation(moving, fixed, T_o, Hypothesis(
        frozenset(frame.groups), tuple(r.pairs), 0.0, 0, 0.0), frame)
    c = r.reference_point
    leak = F @ (held_point(T_c, c) - held_point(T_o, c))
    if not len(F) or np.abs(leak).max() <= FREE_TOLERANCE:
        return r
    size = np.abs(leak).max() * 1e3
    check = kwargs.get('check_penetration', True)
    spacing = kwargs.get('penetration_spacing', 0.005)
    tol = max(kwargs.get('residual_tolerance', 1e-9), 1e-6)
    T_b = T_c.copy()
    T_b[:3, 3] -= F.T @ leak
    d = evaluate_contacts(moving, fixed, T_b, list(r.pairs)).distances
    if np.abs(d).max(initial=0.0) <= tol and (not check or penetration_depth(
            moving, fixed, T_fixed @ T_b, T_fixed, spacing) <= tol):
        return _adopt_relative_pose(r, moving, fixed, T_fixed, T_o, T_b, (
            f' (free directions restored: {size:.3g} mm along a direction the relation leaves '
            'free)'))
    # the orientation of the correction tilts some of the relation's normals (e.g. an
    # edge-edge pair at a slot's entrance) so that they acquire a component along the free
    # direction; solve the relation again with the free components held at the observed ones
    try:
        T_s = _solve_keeping_free(moving, fixed, T_b, T_o, list(r.pairs), F, tol, c)
    except (ValueError, np.linalg.LinAlgError):     # e.g. parallel edges of an edge pair
        T_s = None
    if T_s is not None and (not check or penetration_depth(
            moving, fixed, T_fixed @ T_s, T_fixed, spacing) <= tol):
        r.rotation_change = rotation_log(T_s[:3, :3] @ T_o[:3, :3].T)
        return _adopt_relative_pose(r, moving, fixed, T_fixed, T_o, T_s, (
            f' (re-solved with the free directions held: it moved {size:.3g} mm along a '
            'direction the relation leaves free)'))
    pen = penetration_depth(moving, fixed, T_moving, T_fixed, spacing) if check else 0.0
    if pen <= tol:
        r2 = CorrectionResult(
            T_moving=np.array(T_moving, dtype=float), penetration_before=pen,
            penetration_after=pen, guarded=True,
            status=f'pose passed through ({r.status} moved it {size:.3g} mm along a '
                   'direction the relation leaves free)')
        r2.relation_source = r.relation_source
        return r2
    r.guarded = True
    r.status += (f' (flagged: moved {size:.3g} mm along a direction the relation leaves '
                 'free; the observation penetrates and no correction without it was found)')
    return r


def _adopt_relative_pose(r: CorrectionResult, moving: Polyhedron, fixed: Polyhedron,
                         T_fixed: np.ndarray, T_o: np.ndarray, T_rel: np.ndarray,
                         note: str) -> CorrectionResult:
    """
    Make ``r`` the correction to the relative pose ``T_rel`` (4x4, moving in the fixed frame).

    Sets the world pose, the translation change from the observed relative pose ``T_o``, the
    relation's geometry, constrained directions and residual at ``T_rel``, and appends
    ``note`` to the status. The rotation change is the caller's (unchanged by a pure shift).
    """
    A, g = constraint_matrix(moving, fixed, T_rel, list(r.pairs))
    r.T_moving = T_fixed @ T_rel
    r.translation_change = T_rel[:3, 3] - T_o[:3, 3]
    r.geometry = g
    r.directions = constraint_directions(A, max(moving.size, 1e-6))
    r.max_residual = float(np.abs(g.distances).max(initial=0.0))
    r.status += note
    return r


def _solve_keeping_free(moving: Polyhedron, fixed: Polyhedron, T_start: np.ndarray,
                        T_obs: np.ndarray, pairs: List[ContactPair], F: np.ndarray,
                        tol: float, reference_point: Optional[np.ndarray] = None,
                        iterations: int = 20) -> Optional[np.ndarray]:
    """
    Satisfy ``pairs`` with the reference point's components along ``F`` held at the observed.

    Gauss-Newton from ``T_start`` (moving in fixed frame, 4x4) on the screw ``[w, v]``
    (:func:`~contact_correction.nonlinear_correction.apply_screw`, rotation scaled by the
    moving object's size): the contact distances' rows of Eq. 2 and, as exact rows, the
    change of the reference point ``p`` (``held_point``; the origin by default) along
    the free translations ``F`` (k, 3; fixed frame) that brings it back to ``T_obs``'s
    (``f . (w x p + v) = f . (p_obs - p)``); minimum-norm steps.

    :returns: the pose (4x4) or None when the residual stays above ``tol`` [m].
    """
    L = max(moving.size / 4.0, 1e-6)
    scale = np.array([1.0 / L] * 3 + [1.0] * 3)
    T = np.array(T_start, dtype=float)
    p_obs = held_point(T_obs, reference_point)
    for _ in range(iterations):
        g = evaluate_contacts(moving, fixed, T, pairs)
        t = held_point(T, reference_point)
        leak = F @ (t - p_obs)
        if np.abs(g.distances).max(initial=0.0) <= 1e-3 * tol \
                and np.abs(leak).max(initial=0.0) <= 1e-3 * FREE_TOLERANCE:
            break
        J = np.vstack([constraint_rows(g.points, g.normals),
                       np.hstack([np.cross(t, F), F])]) * scale
        step, *_ = np.linalg.lstsq(J, -np.concatenate([g.distances, leak]), rcond=1e-9)
        step *= scale
        if np.linalg.norm(step[:3]) > 0.3:
            return None
        T = apply_screw(T, step[:3], step[3:])
    g = evaluate_contacts(moving, fixed, T, pairs)
    if np.abs(g.distances).max(initial=0.0) > tol or np.abs(
            F @ (held_point(T, reference_point) - p_obs)).max(initial=0.0) > FREE_TOLERANCE:
        return None
    return T


def push_out_inequalities(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                          T_fixed: np.ndarray, pairs: Sequence[ContactPair],
                          scales: Tuple[float, float] = (1e-3, np.deg2rad(1.0)),
                          spacing: float = 0.005, tolerance: float = 1e-6,
                          rounds: int = 4, max_translation: float = 0.02,
                          max_rotation: float = 0.35, pivot: Optional[np.ndarray] = None,
                          exits_only: bool = False) -> Optional[CorrectionResult]:
    """
    Nearest pose without penetration, non-penetration as inequalities (the last resort).

    The push-outs of :func:`_correct_recognised_paths` bring their pairs *to* contact (the
    non-linear step's equations); with many pairs penetrating (a peg pressed into a corner)
    those equations may have no solution near the observation, or put contact points off
    their elements, and penetration was passed through. Here the pose change ``x`` (rotation
    about ``pivot`` in units of ``scales[1]``, translation of ``pivot`` in units of
    ``scales[0]``, fixed frame) of least ``|x|`` with every pair's distance >= 0 is found
    (SLSQP); pairs found penetrating at the result are added and the search repeated.

    :param pairs: the pairs whose penetration is real at the observation (the guard's).
    :param scales: the stated pose noise (translation [m], rotation [rad]): the metric.
    :param pivot: (3,) the point of the moving object [m, moving model frame] the change turns
        about (the correction's reference point); None: the moving origin.
    :param exits_only: of the vertex pairs found penetrating at a round's result, add only
        those whose face is the vertex's way out (when there are any): a T-peg's stem pushed
        off one wall of its zero-clearance slot into the other had pairs with faces it is not
        behind added, and the next round's constraints were incompatible.
    :param max_translation: largest accepted change of the moving origin [m], as
        ``correct_pose``'s: a pose farther from the observation is not a correction of it (a
        T-peg pulled up out of its slot and pressed into a wall by the noise was pushed 23 mm
        along the slot, ADD 3.3 -> 24 mm).
    :param max_rotation: largest accepted orientation change [rad], as ``correct_pose``'s.
    :returns: the result (``method`` 'nonlinear', the pairs in contact at it as its relation)
        when it leaves no penetration deeper than ``tolerance`` within those limits, else None.
    """
    from scipy.optimize import minimize
    T_o = relative_pose(T_moving, T_fixed)
    sel = list(pairs)

    c_o = held_point(T_o, pivot)        # the pivot at the observation (fixed frame)

    def pose(x: np.ndarray) -> np.ndarray:
        return apply_screw(T_o, x[:3] * scales[1], x[3:] * scales[0], centre=c_o)

    for _ in range(rounds):
        if not sel:
            return None
        # each round from the observation: started from the last round's result, the search
        # with the pairs added diverged (44 against 3.5 noise units for the T-peg 4.6 mm into
        # its slot)
        res = minimize(lambda x: float(x @ x), np.zeros(6), jac=lambda x: 2.0 * x,
                       method='SLSQP',
                       constraints=[{'type': 'ineq', 'fun': lambda x, sel=sel: evaluate_contacts(
                           moving, fixed, pose(x), sel).distances}],
                       options={'ftol': 1e-12, 'maxiter': 200})
        if not np.all(np.isfinite(res.x)):
            return None
        x = res.x
        T = pose(x)
        turn = rotation_log(T[:3, :3] @ T_o[:3, :3].T)
        if np.linalg.norm(T[:3, 3] - T_o[:3, 3]) > max_translation \
                or np.linalg.norm(turn) > max_rotation:
            return None
        pen = penetration_depth(moving, fixed, T_fixed @ T, T_fixed, spacing)
        if pen <= tolerance:
            g = evaluate_contacts(moving, fixed, T, sel)
            on = [p for p, d in zip(sel, g.distances) if abs(d) <= max(tolerance, 1e-7)]
            r = CorrectionResult(T_moving=T_fixed @ T, corrected=True, method='nonlinear',
                                 pairs=on, penetration_after=pen, rotation_change=turn,
                                 status='non-linear push-out, non-penetration as inequalities '
                                        f'({len(sel)} pairs, {len(on)} in contact at the result)')
            return _adopt_relative_pose(r, moving, fixed, T_fixed, T_o, T, '')
        found = detect_contact_relation(moving, fixed, T_fixed @ T, T_fixed, tolerance=0.0,
                                        penetration_tolerance=max(pen, 1e-3))
        d = evaluate_contacts(moving, fixed, T, found).distances if found else np.zeros(0)
        new = np.array([dist < -tolerance and p not in sel for p, dist in zip(found, d)],
                       dtype=bool)
        if exits_only and new.any():
            exits = _really_penetrating(moving, fixed, T, found, new, EXIT_MARGIN)
            new = exits if exits.any() else new
        if not new.any():
            return None
        sel += [p for p, k in zip(found, new) if k]
    return None


def _correct_recognised_paths(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                              T_fixed: np.ndarray, chosen: Hypothesis, frame: FrameCandidates,
                              guard: Optional[np.ndarray] = None,
                              recognition_margin: Optional[float] = None,
                              guard_limits: Optional[Tuple[float, float]] = None,
                              noise: Optional[Tuple[float, float]] = None,
                              **kwargs: Any) -> CorrectionResult:
    """
    Correct one frame with a recognised relation, with fallbacks (every path).

    Correct one frame with a recognised relation, falling back to the frame's next best
    relations and finally to pushing a penetrating observation out.

    :param chosen: the relation chosen for the frame.
    :param frame: the frame's candidates (pool and scored relations).
    :param guard: the pool's guard flags (pairs whose penetration is real).
    :param recognition_margin: the recognition's search margin [m]: contact points may end up
        this far outside their elements (default: ``kwargs['element_margin']`` only).
    :param guard_limits: the correction-size guard (translation of the moving origin [m],
        rotation [rad]; ``max_correction_sigma`` times the stated noise): a correction with the
        chosen relation or a fallback beyond either is refused; the relations nested in the
        chosen one (fewer constraints, best score first) are tried, then the non-penetration
        only correction (a penetrating observation pushed out) or the observation itself; the
        result is flagged ``guarded``. None: no guard.
    :param noise: the stated pose noise (translation [m], rotation [rad]). A push-out (the
        non-linear step only) is the feasible pose nearest the observation in these units,
        turning about ``kwargs['reference_point']`` (the moving origin when not given), not
        about the fixed model's origin in the step's default metric: that one tilted a peg
        touching a block with a corner about the block's top-face centre, 0.15 mm of ADD
        added to a 0.4 mm observation (contact_tracks: offline frames worse by more than
        sigma 1 -> 0 on two noise seeds). None: the step's default metric.
    :param kwargs: passed to :func:`~contact_correction.correction.correct_pose`.
    """
    kwargs = dict(kwargs)
    kwargs.setdefault('prune_off_element', True)
    if recognition_margin is not None:
        # a recognised face-face contact may end with some of its pairs just beyond the
        # overlap (the free coordinates are kept as observed); within the recognition margin
        # that is accepted, penetration is still checked
        kwargs['element_margin'] = max(kwargs.get('element_margin', 0.0), recognition_margin)
    check = kwargs.get('check_penetration', True)
    spacing = kwargs.get('penetration_spacing', 0.005)
    pen = penetration_depth(moving, fixed, T_moving, T_fixed, spacing) if check \
        else float('nan')
    if check:
        kwargs['penetration_before'] = pen      # every attempt starts from the observation
    tol = max(kwargs.get('residual_tolerance', 1e-9), 1e-6)
    # the point push-outs turn about: the correction's reference point, else the moving origin
    pivot = np.zeros(3) if kwargs.get('reference_point') is None \
        else np.asarray(kwargs['reference_point'], dtype=float).reshape(3)

    def push_out(last_resort: bool = False) -> Optional[CorrectionResult]:
        """
        Push the pose out with the non-linear step only.

        Non-linear step only (the feasible pose nearest the observation) on the pool's pairs
        that penetrate; pairs found penetrating at the attempt's pose are
        added and the attempt repeated. At the observation only the guarded pairs count
        (real penetration: the face is the vertex's nearest exit), except ``last_resort``
        when none is: then the penetrating pairs on the face of the deepest one (a peg
        inserted flush has its vertices on the block's front plane, which the nearest-exit
        test takes as their exit although they are 2-3 mm into a slot wall).
        """
        if not frame.pool:
            return None
        pool = list(frame.pool)
        sel = np.zeros(len(pool), dtype=bool)
        T_try = np.asarray(T_moving, dtype=float)
        left = float('nan')     # [m] penetration left at T_try (the last attempt's)
        kw = dict(kwargs, optimal=False, nonlinear_pivot=pivot, nonlinear_length_scale=(
            noise[0] / noise[1] if noise is not None else None))
        for _ in range(3):
            T_rel = relative_pose(T_try, T_fixed)
            if T_try is not T_moving:
                # pairs penetrating at the attempt's pose that the observation's pool lacks
                # (e.g. edges that cross only once the pose is pushed)
                extra = [p for p in detect_contact_relation(
                    moving, fixed, T_try, T_fixed, tolerance=0.0,
                    penetration_tolerance=max(pen, 1e-3)) if p not in pool]
                pool += extra
                sel = np.concatenate([sel, np.zeros(len(extra), dtype=bool)])
            g = evaluate_contacts(moving, fixed, T_rel, pool)
            new = g.distances < -tol
            if guard is not None and len(guard) == len(new) and T_try is T_moving:
                # (the observation's round: no pair selected yet)
                if last_resort and not np.any(new & guard) and np.any(new):
                    k = int(np.argmin(np.where(new, g.distances, np.inf)))
                    face = _penetrated_face(pool[k])
                    new &= np.array([_penetrated_face(p) == face for p in pool], dtype=bool)
                else:
                    # each vertex through its nearest face only, as at the attempts' poses
                    # below: brought to contact with two faces the guard's slack lets through
                    # (0.25 mm at the demo's noise), a vertex is moved onto their edge (a peg
                    # 1 mm into slot_block's zero-clearance slot, a corner 0.70 mm into a wall
                    # and 0.93 mm below the top face: lifted 0.88 mm, out of the slot)
                    new = _nearest_exit_per_vertex(pool, g.distances, new & guard)
            elif T_try is not T_moving:     # the guard is the observation's
                real = _really_penetrating(moving, fixed, T_rel, pool, new & ~sel,
                                           EXIT_MARGIN)
                if np.any(real):
                    new = real | (new & sel)
                else:
                    # penetration along edges only: the pairs behind their plane by no more
                    # than the penetration left (plus the exit margin), else every pair behind
                    # its plane, as the last resort. A peg 2.7 mm into a zero-clearance hole,
                    # pushed off a wall with 0.18 mm left along its edges, had its bottom
                    # vertices (2.5-4.3 mm below the top face's plane) pushed up through the
                    # top face: 2.7 mm along the direction the walls leave free
                    shallow = new & ~sel & (g.distances >= -(left + EXIT_MARGIN))
                    if np.any(shallow):
                        new = shallow | (new & sel)
                    elif left <= tol:
                        # nothing penetrates there: pairs behind their planes only, none to
                        # push (the peg 1.3 mm into the hole, its corners brought to the walls,
                        # was lifted by its bottom corners onto the top face: 0.13 -> 1.33 mm)
                        new = new & sel
            if not np.any(new & ~sel):
                break
            added = new & ~sel
            sel |= new
            r = correct_pose(moving, fixed, T_moving, T_fixed,
                             [p for p, s in zip(pool, sel) if s], **kw)
            r.relation_source = 'recognised, push-out'
            if r.corrected:
                return r
            if r.T_nonlinear is None and T_try is not T_moving:
                # not satisfiable with every pair as a contact: pairs brought to contact by
                # the previous attempt would separate on the way out of the new penetration
                # (a peg pushed off a bar-slot wall, still 2.5 mm into the stem wall): the
                # new penetrating pairs on the face of the deepest one only
                k = int(np.argmin(np.where(added, g.distances, np.inf)))
                face = _penetrated_face(pool[k])
                sel = added & np.array([_penetrated_face(p) == face for p in pool])
                r = correct_pose(moving, fixed, T_moving, T_fixed,
                                 [p for p, s in zip(pool, sel) if s], **kw)
                r.relation_source = 'recognised, push-out'
                if r.corrected:
                    return r
            if r.T_nonlinear is None:
                break
            T_try = r.T_nonlinear
            # a degenerate attempt has no penetration measured: measured here, or the rule
            # for penetration along edges below was skipped and every pair behind its plane
            # added (the peg 1.3 mm into the hole, its corners brought to the walls, was
            # lifted onto the top face: ADD-sym 0.13 -> 1.33 mm)
            left = r.penetration_after if np.isfinite(r.penetration_after) else \
                penetration_depth(moving, fixed, T_try, T_fixed, spacing)
        return None

    def over(r: CorrectionResult) -> bool:
        if guard_limits is None or not r.corrected:
            return False
        return bool(np.linalg.norm(r.translation_change) > guard_limits[0]
                    or np.linalg.norm(r.rotation_change) > guard_limits[1])

    def size(r: CorrectionResult) -> str:
        return (f'{np.linalg.norm(r.translation_change) * 1e3:.2f} mm / '
                f'{np.degrees(np.linalg.norm(r.rotation_change)):.2f} deg')

    def refuse(r: CorrectionResult, why: str) -> CorrectionResult:
        r.T_moving = np.array(T_moving, dtype=float)
        r.corrected, r.guarded, r.method = False, True, 'passthrough'
        r.status += f' (guard: {why} refused)'
        return r

    def guarded(r: CorrectionResult, why: str) -> CorrectionResult:
        r.guarded = True
        r.status += f' (guard: {why})'
        return r

    def valid(r: CorrectionResult, h: Hypothesis, depth: int = 0) -> CorrectionResult:
        """
        Check a correction with ``h`` against the relation's own free directions.

        A face-face group (or a single vertex-face / face-vertex one) is a contact only when
        moving the corrected pose into it penetrates;
        one whose faces meet only along a boundary line (a peg side face level with a hole's
        wall while the peg stands on the top face: the rim is convex, nothing stops the peg
        along the wall's normal) is dropped and the frame corrected with the rest of ``h``.
        The change along the directions ``h`` leaves free (as recognised: a face-face group
        constrains along its fixed face's normal) is restored when the pose keeps its contacts
        and stays out of penetration there (the non-linear step may end at a configuration
        where boundary pairs add constraints, e.g. a T-peg pulled to the slot's entrance).
        """
        if not r.corrected or not h.state or not frame.pool:
            return r
        T_o, T_c = relative_pose(T_moving, T_fixed), relative_pose(r.T_moving, T_fixed)
        F = _recognised_free_translation(moving, fixed, T_o, h, frame)
        c = r.reference_point
        leak = F @ (held_point(T_c, c) - held_point(T_o, c))
        if len(F) and np.abs(leak).max() > FREE_TOLERANCE:
            T_b = T_c.copy()
            T_b[:3, 3] -= F.T @ leak
            used = set(r.pairs)
            kept = [p for p in h.pairs if p in used and VERTEX in (p.moving_type, p.fixed_type)]
            d = evaluate_contacts(moving, fixed, T_b, kept).distances if kept else np.zeros(0)
            if np.abs(d).max(initial=0.0) <= tol and (not check or penetration_depth(
                    moving, fixed, T_fixed @ T_b, T_fixed, spacing) <= tol):
                r.T_moving = T_fixed @ T_b
                r.translation_change = T_b[:3, 3] - T_o[:3, 3]
                # the relation at the returned pose: the pairs still in contact there (pushed
                # pairs left behind by the restored free components are not)
                A, g = constraint_matrix(moving, fixed, T_b, list(r.pairs))
                on = np.abs(g.distances) <= tol
                r.pairs = [p for p, k in zip(r.pairs, on) if k]
                r.geometry = ContactGeometry(g.distances[on], g.points[on], g.normals[on])
                r.directions = constraint_directions(A[on], max(moving.size, 1e-6))
                r.max_residual = float(np.abs(g.distances[on]).max(initial=0.0))
                r.status += (f' (free directions restored: {np.abs(leak).max() * 1e3:.3g} mm '
                             'along a direction the relation leaves free)')
                T_c = T_b
            elif check and pen <= tol:
                # the relation cannot be enforced without moving along a direction it leaves
                # free (a degenerate configuration at the corrected pose): a silently wrong
                # pose is worse than no correction
                r2 = CorrectionResult(
                    T_moving=np.array(T_moving, dtype=float), penetration_before=pen,
                    penetration_after=pen,
                    status=f'pose passed through ({r.status} moved it '
                           f'{np.abs(leak).max() * 1e3:.3g} mm along a direction the '
                           'relation leaves free)')
                r2.relation_source = r.relation_source
                return r2
        if not check or depth > 1:
            return r
        spurious = set()
        for key in h.state:
            if key[0] not in ('ff', 'fv', 'vf'):
                continue
            T_in = T_c.copy()
            if key[0] == 'fv':      # a fixed vertex on a moving face: the face advances
                T_in[:3, 3] += CONTACT_PROBE * (T_c[:3, :3] @ moving.face_normals[key[1]])
                depth = _vertex_depth(T_in, fixed.vertices[key[2]], moving, inverse=True)
            elif key[0] == 'vf':
                T_in[:3, 3] -= CONTACT_PROBE * fixed.face_normals[key[2]]
                depth = _vertex_depth(T_in, moving.vertices[key[1]], fixed, inverse=False)
            else:
                T_in[:3, 3] -= CONTACT_PROBE * fixed.face_normals[key[2]]
                depth = _face_contact_depth(moving, fixed, T_in, key[1], key[2], spacing)
            if depth < 0.5 * CONTACT_PROBE:
                spurious.add(key)
        if not spurious:
            return r
        h2 = frame.hypothesis(h.state - frozenset(spurious))
        note = (f' (dropped {len(spurious)} face-face group(s) meeting only along a boundary '
                'at the corrected pose)')
        if h2.pairs:
            r2 = correct_pose(moving, fixed, T_moving, T_fixed, list(h2.pairs), **kwargs)
            r2.relation_source = r.relation_source
            if r2.corrected and not over(r2):
                r2 = valid(r2, h2, depth + 1)
                r2.status += note
                return r2
        elif pen <= tol:
            r2 = CorrectionResult(T_moving=np.array(T_moving, dtype=float),
                                  status='pose passed through' + note,
                                  penetration_before=pen, penetration_after=pen)
            r2.relation_source = r.relation_source
            return r2
        return r

    first: Optional[CorrectionResult] = None
    oversize: List[CorrectionResult] = []   # non-penetrating corrections beyond the guard
    if chosen.pairs:
        r = correct_pose(moving, fixed, T_moving, T_fixed, list(chosen.pairs), **kwargs)
        r.relation_source = 'recognised'
        if r.corrected and not over(r):
            return valid(r, chosen)
        if r.corrected:
            # far beyond the stated noise: a relation with fewer constraints, else only
            # non-penetration, else the observation (never silently)
            why = (f'the chosen relation ({chosen.rank} constraints) needed {size(r)}, over '
                   f'{guard_limits[0] * 1e3:.2f} mm / {np.degrees(guard_limits[1]):.2f} deg')
            nested = sorted((h for h in frame.hypotheses.values()
                             if h.state < chosen.state and 0 <= h.rank < chosen.rank
                             and np.isfinite(h.score)), key=lambda h: h.score)
            for h in nested[:MAX_FALLBACKS]:
                if not h.pairs:
                    break
                r2 = correct_pose(moving, fixed, T_moving, T_fixed, list(h.pairs), **kwargs)
                r2.relation_source = 'recognised, guard'
                if r2.corrected and not over(r2):
                    return guarded(valid(r2, h),
                                   why + f'; a nested relation of rank {h.rank} used')
            if check and pen > tol:
                r2 = push_out()
                if r2 is not None:
                    r2.relation_source = 'recognised, guard'
                    guarded(r2, why + '; only the penetration removed')
                    if not over(r2):
                        return r2
                    oversize.append(r2)
            if not check or pen <= tol:
                r2 = CorrectionResult(T_moving=np.array(T_moving, dtype=float),
                                      status='pose passed through', penetration_before=pen,
                                      penetration_after=pen)
                r2.relation_source = 'recognised, guard'
                return guarded(r2, why + '; no smaller feasible correction')
            refuse(r, why)
        first = r
    elif not check or pen <= tol:
        r = CorrectionResult(T_moving=np.array(T_moving, dtype=float),
                             status='no contact (recognised: the observation is '
                                    'explained best without contact); pose passed '
                                    'through', penetration_before=pen,
                             penetration_after=pen)
        r.relation_source = 'recognised'
        return r
    if check and pen > tol and not (first is not None and first.guarded):
        # only what penetrates: the smallest change that removes the penetration, rather than
        # another relation of the frame that may constrain a free direction. Not with the
        # chosen relation's pairs when its own correction failed (penetration left, contact
        # points off their elements): the peg 1.3 mm into the hole, still held against one of
        # its walls by the temporal model, was lifted back onto the top face (the demo's
        # peg_in_hole, scene seed 3: ADD-sym 0.27 -> 1.33 mm; contact_tracks' eight extra draws:
        # frames worse by more than sigma 6 / 21 / 4 -> 5 / 20 / 3)
        r = push_out()
        if r is not None:
            r = valid(r, chosen, depth=2)    # its free directions only (pairs were added)
            r.status += (' (push-out: the chosen relation ' + (
                f'could not be enforced: {first.status}' if first is not None else 'is free')
                + ' and the observation penetrates)')
            if not over(r):
                return r
            oversize.append(r)
    order = [h for h in frame.ranked() if h.state != chosen.state and h.pairs]
    for k, h in enumerate(order[:MAX_FALLBACKS]):
        r = correct_pose(moving, fixed, T_moving, T_fixed, list(h.pairs), **kwargs)
        r.relation_source = f'recognised, fallback {k + 1}'
        if r.corrected and over(r):
            refuse(r, f'fallback correction {size(r)}')
        if r.corrected and chosen.state:
            # another relation of the frame must not move the pose along a direction the
            # chosen one leaves free (restored when the pose stays feasible, else the next
            # fallback): a T-peg entering its slot whose chosen relation left 17 um of
            # penetration was put back 2.2 mm to the slot's entrance by the block's front face
            r2 = valid(r, chosen, depth=2)
            if not r2.corrected:
                first = first or r
                continue
            r = r2
        if r.corrected:
            r.status += f' (fallback: relation {k + 2} of the frame; the chosen one: ' \
                        f'{first.status if first else "free"})'
            return r
        first = first or r
    if check and pen > tol and not (first is not None and first.guarded):
        # last resort: the penetrating pairs alone (also after a free choice, whose push-out
        # above counted only guarded pairs: a T-peg 5.9 mm into its slot's wall, no pair
        # passing the nearest-exit test, had its penetration passed through)
        r = push_out(last_resort=True)
        if r is not None:
            r.status += ' (push-out: no recognised relation could be enforced and the ' \
                        'observation penetrates)'
            if not over(r):
                return r
            oversize.append(r)
    if check and pen > tol and not oversize and guard is not None \
            and len(guard) == len(frame.pool):
        # the last resort, when no correction at all was found: non-penetration as
        # inequalities from the pairs that really penetrate (the T-peg pressed into the
        # slot's corner at lag 1 of contact_tracks: every relation and push-out above failed,
        # 2.1 mm of penetration was passed through)
        at_obs = evaluate_contacts(moving, fixed, relative_pose(T_moving, T_fixed),
                                   list(frame.pool)).distances if frame.pool else np.zeros(0)
        real = [p for p, d, g in zip(frame.pool, at_obs, guard) if g and d < -tol]
        # no pair passes the guard's nearest-exit test (a T-peg 4.6 mm into its zero-clearance
        # slot): every penetrating pair, its result accepted only within the guard
        unguarded = not real
        if unguarded:
            real = [p for p, d in zip(frame.pool, at_obs) if d < -tol]
        scales = noise or guard_limits or (1e-3, np.deg2rad(1.0))
        # then again adding only pairs whose face is the vertex's way out (a T-peg's stem
        # pushed off one wall into the other: incompatible constraints), kept only within the
        # guard; a first search's result beyond the guard (from guarded pairs) is kept for the
        # smallest-over-the-guard rule below
        for exits_only in (False, True):
            r = push_out_inequalities(
                moving, fixed, T_moving, T_fixed, real, scales, spacing, tol,
                max_translation=kwargs.get('max_translation', 0.02),
                max_rotation=kwargs.get('max_rotation', 0.35), pivot=pivot,
                exits_only=exits_only)
            if r is None:
                continue
            r.penetration_before = pen
            r.relation_source = 'recognised, push-out'
            guarded(r, 'no recognised relation could be enforced; only the penetration '
                       f'removed ({size(r)})')
            if not over(r):
                return r
            if not unguarded and not exits_only:    # (the others: 17.7 / 18.8 mm seen)
                oversize.append(r)
    if oversize:
        # every non-penetrating correction found is beyond the guard: the smallest (stated
        # noise units), flagged, rather than penetration passed through
        w = np.array([guard_limits[0], guard_limits[1]])
        r = min(oversize, key=lambda c: float(np.hypot(
            np.linalg.norm(c.translation_change) / w[0],
            np.linalg.norm(c.rotation_change) / w[1])))
        return guarded(r, f'{size(r)} over the limits, the smallest non-penetrating '
                          'correction found')
    if first is None:
        first = CorrectionResult(T_moving=np.array(T_moving, dtype=float),
                                 status='no usable relation; pose passed through',
                                 penetration_before=pen)
    first.relation_source = 'recognised'
    return first


def _penetrated_face(pair: ContactPair) -> Tuple[str, int]:
    """Return the face a pair's distance is measured to: ('fixed' | 'moving', index)."""
    if pair.fixed_type == FACE:
        return ('fixed', pair.fixed_index)
    if pair.moving_type == FACE:
        return ('moving', pair.moving_index)
    return ('edge', -1)


def _face_boundary_samples(poly: Polyhedron, face: int, spacing: float) -> np.ndarray:
    """Points [m] every ``spacing`` along the edges bounding ``face`` (model frame), cached."""
    key = ('face boundary', int(face), float(spacing))
    pts = poly._samples.get(key)
    if pts is None:
        out = []
        for e in np.flatnonzero(np.any(poly.edge_faces == face, axis=1)):
            k = max(1, int(np.ceil(poly.edge_lengths[e] / spacing)))
            a, b = poly.vertices[poly.edge_vertices[e]]
            out.append(a + (np.arange(k + 1) / k)[:, None] * (b - a))
        pts = np.vstack(out) if out else np.zeros((0, 3))
        poly._samples[key] = pts
    return pts


def _face_contact_depth(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                        moving_face: int, fixed_face: int, spacing: float) -> float:
    """
    Interpenetration depth [m] of two faces' boundaries at ``T_rel`` (moving in fixed frame).

    :func:`~contact_correction.contact_relation.penetration_depth` restricted to the points
    sampled along the edges of the two faces: after a probe step into a face-face contact,
    the faces overlap over an area when some of these points are inside the other solid
    (by about the step), along a boundary line only when none is.
    """
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    depth = 0.0
    for pts, other in ((_face_boundary_samples(moving, moving_face, spacing) @ R.T + t, fixed),
                       ((_face_boundary_samples(fixed, fixed_face, spacing) - t) @ R, moving)):
        pts = pts[other.in_bbox(pts)]
        if len(pts) == 0:
            continue
        inside = other.contains(pts) > 0.5 + 1e-6
        if np.any(inside):
            depth = max(depth, float(other.distance_to_surface(pts[inside]).max()))
    return depth


def _vertex_depth(T_rel: np.ndarray, x: np.ndarray, solid: Polyhedron, inverse: bool) -> float:
    """
    Depth [m] of one vertex inside ``solid`` (0 outside or on its surface).

    :param T_rel: moving pose in the fixed frame (4, 4).
    :param x: the vertex in its own model frame (3,): the moving object's (``inverse`` False,
        tested in the fixed solid) or the fixed object's (``inverse`` True, tested in the
        moving solid).
    """
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    p = ((x - t) @ R if inverse else R @ x + t)[None]
    if solid.contains(p)[0] <= 0.5 + 1e-6:
        return 0.0
    return float(solid.distance_to_surface(p)[0])


def _recognised_free_translation(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                                 h: Hypothesis, frame: FrameCandidates) -> np.ndarray:
    """
    Return the translations (rows, fixed frame) ``h`` leaves free, as the recognition sees it.

    The separating-plane normals of ``h``'s pairs at ``T_rel`` (the observed pose, moving in
    fixed frame), every pair of a face-face group taking its fixed face's normal (as the
    recognition's rank does); their null space, orthonormal rows (k, 3).
    """
    g = evaluate_contacts(moving, fixed, T_rel, list(h.pairs))
    N = g.normals.copy()
    index = {p: i for i, p in enumerate(h.pairs)}
    for key in h.state:
        if key[0] == 'ff' and key in frame.groups:
            for j in frame.groups[key]:
                i = index.get(frame.pool[j])
                if i is not None:
                    N[i] = fixed.face_normals[key[2]]
    if len(N) == 0:
        return np.eye(3)
    _, s, Vt = np.linalg.svd(N)
    r = int(np.sum(s > 1e-6 * max(1.0, s[0])))
    return Vt[r:]


def guard_limits(options: RecognitionOptions) -> Optional[Tuple[float, float]]:
    """
    Return the correction-size guard of ``options``.

    :returns: (translation [m], rotation [rad]) = ``max_correction_sigma`` times the stated
        noise, or None when the guard is disabled (``max_correction_sigma`` 0).
    """
    k = float(options.max_correction_sigma)
    if k <= 0:
        return None
    sigma_t, sigma_r = stated_noise(options)
    return k * sigma_t, k * sigma_r


def stated_noise(options: RecognitionOptions) -> Tuple[float, float]:
    """Return the stated pose noise of ``options``: (translation [m], rotation [rad])."""
    return float(options.sigma_translation), float(options.sigma_rotation)


def _nearest_exit_per_vertex(pool: Sequence[ContactPair], distances: np.ndarray,
                             mask: np.ndarray) -> np.ndarray:
    """
    Keep, of each vertex's pairs in ``mask``, the one(s) it is least deep behind.

    A vertex penetrating two faces is out of the solid once through either; brought to
    contact with both, it is moved onto their common edge. The pairs whose depth is within
    :data:`EXIT_MARGIN` of the vertex's shallowest are kept (a vertex at a corner keeps both);
    edge-edge pairs are kept.

    :param distances: (N,) signed distances [m] of the pool's pairs (negative: penetrating).
    :param mask: (N,) bool, the pairs considered.
    :returns: the reduced mask (N,) bool.
    """
    out = np.array(mask, dtype=bool)
    shallowest: Dict[Tuple[str, int], float] = {}
    keys: Dict[int, Tuple[str, int]] = {}
    for k in np.flatnonzero(out):
        p = pool[k]
        if p.moving_type == VERTEX:
            keys[k] = ('moving', p.moving_index)
        elif p.fixed_type == VERTEX:
            keys[k] = ('fixed', p.fixed_index)
        else:
            continue
        shallowest[keys[k]] = max(shallowest.get(keys[k], -np.inf), float(distances[k]))
    for k, key in keys.items():
        out[k] = distances[k] >= shallowest[key] - EXIT_MARGIN
    return out


def _really_penetrating(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                        pool: Sequence[ContactPair], mask: np.ndarray, tol: float
                        ) -> np.ndarray:
    """
    Keep the vertex pairs whose vertex is inside the other solid with this face its exit.

    A vertex behind a face's plane is penetrating that face only when it is inside the other
    solid and the face is (within ``tol``) the nearest part of its surface: a vertex in a
    block's slot lies below the block's top-face plane but outside the block, and pushing it
    out through the top face moves the pose by the slot's depth, along directions the true
    contact leaves free. Edge-edge pairs are kept.

    :param T_rel: moving pose in the fixed frame (4, 4).
    :param pool: the frame's pairs.
    :param mask: the pairs considered (N,) bool.
    :param tol: slack [m] on the nearest-exit test.
    :returns: the reduced mask (N,) bool.
    """
    out = np.array(mask, dtype=bool)
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    Ri, ti = R.T, -R.T @ t
    for k in np.flatnonzero(out):
        p = pool[k]
        if p.moving_type == VERTEX:
            x, solid, f = R @ moving.vertices[p.moving_index] + t, fixed, p.fixed_index
        elif p.fixed_type == VERTEX:
            x, solid, f = Ri @ fixed.vertices[p.fixed_index] + ti, moving, p.moving_index
        else:
            continue
        if solid.contains(x[None])[0] <= 0.5:
            out[k] = False
        else:
            out[k] = float(solid.face_distance(f, x[None])[0]) \
                <= float(solid.distance_to_surface(x[None])[0]) + tol
    return out


class ContactCorrector:
    """
    Correction of a track as it arrives: recognition with the temporal model, then correction.

    ``lag`` 0 (online, :meth:`update`): each frame is corrected as it arrives, with the
    relation at the end of the temporal model's least-cost path (hysteresis) and the online
    checks of that choice. A contact change is seen only once the frames after it confirm
    it: the first frame after a release is still corrected with the released contact.

    ``lag`` L > 0 (fixed-lag smoothing, :meth:`push`): a frame is corrected once the L frames
    after it have arrived, with the relation the offline Viterbi back-tracking chooses over
    the frames seen so far (as :func:`correct_trajectory`, without its second pass). The
    result comes L frames late; at a gap, :meth:`flush` decides the frames still waiting.

    :param moving: moving object's polyhedron.
    :param fixed: fixed object's polyhedron.
    :param recognition: recognition options (noise model, margins, switching cost).
    :param lag: frames a result waits for the evidence of the frames after it (0: online).
    :param kwargs: correction options for :func:`~contact_correction.correction.correct_pose`.
    :raises ValueError: on a negative ``lag``.
    """

    def __init__(self, moving: Polyhedron, fixed: Polyhedron,
                 recognition: Optional[RecognitionOptions] = None, lag: int = 0,
                 **kwargs: Any) -> None:
        if int(lag) != lag or lag < 0:
            raise ValueError(f'lag must be a whole number of frames >= 0, got {lag}')
        self.moving, self.fixed = moving, fixed
        self.recognizer = RelationRecognizer(moving, fixed, recognition)
        # the area check of every candidate where the back-tracking chooses (as offline);
        # online only the chosen relation is checked (RelationTracker.update)
        self.recognizer.area_check = bool(lag and self.recognizer.options.area_contact_check)
        self.tracker = RelationTracker(self.recognizer)
        self.lag = int(lag)
        self.kwargs = kwargs
        #: frames waiting for their relation: (tag, T_moving, T_fixed, candidates, guard)
        self._pending: List[Tuple[Any, np.ndarray, np.ndarray, FrameCandidates,
                                  np.ndarray]] = []

    @property
    def pending(self) -> int:
        """Frames pushed whose result has not been returned yet."""
        return len(self._pending)

    def reset(self) -> None:
        """Forget the track's contact states and the frames waiting (after a jump in time)."""
        self.tracker.reset()
        self._pending.clear()

    def update(self, T_moving: np.ndarray, T_fixed: np.ndarray) -> CorrectionResult:
        """
        Correct the next frame of the track online (``lag`` 0).

        :param T_moving: observed moving pose (4, 4).
        :param T_fixed: fixed pose (4, 4), in the same frame.
        :raises ValueError: with ``lag`` > 0 (use :meth:`push`).
        """
        if self.lag:
            raise ValueError(f'ContactCorrector with lag {self.lag}: results come late, '
                             'use push() and flush()')
        return self.push(T_moving, T_fixed)[0][1]

    def push(self, T_moving: np.ndarray, T_fixed: np.ndarray, tag: Any = None
             ) -> List[Tuple[Any, CorrectionResult]]:
        """
        Add the next frame; return the frames decided by it, oldest first, with their tags.

        ``lag`` 0: this frame. ``lag`` L: the frame L frames back, once there is one. A frame
        with a non-finite pose decides every waiting frame (a gap: the temporal model starts
        again after it) and is returned itself, passed through.

        :param T_moving: observed moving pose (4, 4).
        :param T_fixed: fixed pose (4, 4), in the same frame.
        :param tag: anything identifying the frame to the caller (e.g. its stamp).
        """
        T_moving = np.asarray(T_moving, dtype=float)
        T_fixed = np.asarray(T_fixed, dtype=float)
        if not (np.all(np.isfinite(T_moving)) and np.all(np.isfinite(T_fixed))):
            out = self.flush()
            self.tracker.reset()
            return out + [(tag, correct_pose(self.moving, self.fixed, T_moving, T_fixed,
                                             **self.kwargs))]
        h, fc = self.tracker.update(T_moving, T_fixed, keep_history=self.lag > 0)
        self._pending.append((tag, T_moving, T_fixed, fc, self.recognizer.last_guard()))
        if not self.lag:
            return self._correct([h])
        if len(self._pending) <= self.lag:
            return []
        # the back-tracking needs the frames from the one decided on: the oldest is dropped
        out = self._correct(self.tracker.backtrack()[:1])
        self.tracker.history.pop(0)
        return out

    def flush(self) -> List[Tuple[Any, CorrectionResult]]:
        """
        Decide the waiting frames now, with the evidence so far (oldest first, with tags).

        The temporal model's state is kept: frames pushed after a flush continue the track.
        """
        if not self._pending:
            return []
        out = self._correct(self.tracker.backtrack())
        self.tracker.history.clear()
        return out

    def _correct(self, chosen: Sequence[Hypothesis]) -> List[Tuple[Any, CorrectionResult]]:
        """Correct the oldest waiting frames, one per relation of ``chosen``."""
        out = []
        for h in chosen:
            tag, T_moving, T_fixed, fc, guard = self._pending.pop(0)
            out.append((tag, correct_recognised(
                self.moving, self.fixed, T_moving, T_fixed, h, fc, guard,
                self.recognizer.margin, guard_limits(self.recognizer.options),
                stated_noise(self.recognizer.options), **self.kwargs)))
        return out


def correct_trajectory(moving: Polyhedron, fixed: Polyhedron, moving_poses: np.ndarray,
                       fixed_poses: np.ndarray,
                       relations: Optional[Sequence[Optional[Sequence[ContactPair]]]] = None,
                       recognition: Optional[RecognitionOptions] = None,
                       smooth: bool = True, **kwargs: Any) -> List[CorrectionResult]:
    """
    Correct every frame of an observed trajectory.

    :param moving_poses: observed moving-object poses, shape (N, 4, 4).
    :param fixed_poses: fixed-object poses, shape (N, 4, 4), or one (4, 4) pose for all frames.
    :param relations: per-frame contact relations (entries None: recognised / detected).
    :param recognition: recognise the relations (model selection + temporal model) with these
        options; None = detect each frame with ``kwargs['tolerance']`` (first version).
    :param smooth: with ``recognition``, back-track the whole track (offline Viterbi) instead
        of the online choice.
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
    chosen = frames = guards = None
    if recognition is not None:
        rec = RelationRecognizer(moving, fixed, recognition)
        chosen, frames, guards = recognise_track(rec, Tm, Tf, smooth=smooth,
                                                 return_guards=True)
    out = []
    for k in range(len(Tm)):
        rel = relations[k] if relations is not None else None
        if rel is None and chosen is not None and np.all(np.isfinite(Tm[k])) \
                and np.all(np.isfinite(Tf[k])):
            out.append(correct_recognised(moving, fixed, Tm[k], Tf[k], chosen[k], frames[k],
                                          guards[k], rec.margin, guard_limits(recognition),
                                          stated_noise(recognition), **kwargs))
            continue
        r = correct_pose(moving, fixed, Tm[k], Tf[k], rel, **kwargs)
        r.relation_source = 'given' if rel is not None else 'detected'
        out.append(r)
    return out


def trajectory_components(results: Sequence[CorrectionResult], moving_poses: np.ndarray,
                          fixed_poses: np.ndarray, axes: Optional[np.ndarray] = None
                          ) -> Dict[str, np.ndarray]:
    """
    Positions of the observed and corrected origins in the fixed frame, projected on axes.

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
