"""
Optimal (linear) vision error correction (Section 3, Eqs. 2-9; Takamatsu et al. 2002).

Given the observed pose ``(Theta_E, t_E)`` and a pose ``(Theta_S, t_S)`` satisfying the contact
relation (the non-linear step), remove from the correction every displacement that the contacts
do not constrain:

1. Eq. 2: the infinitesimal screws ``[s0, s1]`` keeping the relation satisfy, for every contact
   ``i`` and separating plane ``j``, ``f_ij . s1 + (p_i x f_ij) . s0 = 0``
   (:func:`constraint_matrix`).
2. Eq. 3: eliminating ``s1`` gives the rotational constraint ``g_i . s0 = 0``; its rows span
   the constrained rotation axes and its rank (0-3) selects the orientation rule
   (:func:`rotational_constraint`, :func:`rotational_constraint_rank`).
3. Optimal orientation by rank: 3 -> ``Theta_S``; 0 -> ``Theta_E``; 2 -> Eqs. 4-5 (remove the
   rotation about the free axis); 1 -> Eqs. 6-7 with ``R_m`` of Eq. 8 (edge of the moving object
   on a face) or Eq. 9 (face of the moving object on an edge), and a general numerical method
   for every other rank-1 relation (:func:`optimal_orientation_numerical`).
4. Translation: with the orientation fixed the contact distances are affine in the translation;
   the minimum-norm least-squares change of the observed translation that zeroes them lies in
   the span of the separating-plane normals, so the displacement along the unconstrained
   translation directions is exactly zero (Fig. 9) (:func:`optimal_translation`). Zero for
   which point of the moving object: the chapter's is the model origin; any reference point
   may be held instead (:func:`reference_translation`; ``correct_pose``'s
   ``reference_point``).

Reading of Eqs. 4-7. As printed, Eq. 5 gives ``Theta_opt = R(m, alpha) Theta_S`` and Eq. 7
``Theta_opt = R_z(alpha) Theta_S``; a rotation of the corrected orientation about a constrained
axis would break the contact relation (e.g. tilt a cube resting on a table). The text's intent --
``Theta_opt`` satisfies the relation and differs from the observation only by a rotation about
constrained axes -- is met with ``Theta_E`` and ``Theta_S`` exchanged, which is what we
implement:

* rank 2 (Eqs. 4-5): ``R(m, alpha) Theta_E = R_z(beta) Theta_S`` with ``m`` in the xy-plane of
  frame A (z = free axis); ``Theta_opt = R(m, alpha) Theta_E = R_z(beta) Theta_S``;
* rank 1 (Eqs. 6-7): ``R_z(alpha) Theta_E = R_m(beta, gamma) Theta_S`` with z = the constrained
  axis; ``Theta_opt = R_z(alpha) Theta_E = R_m(beta, gamma) Theta_S``.

All vectors are expressed in the fixed object's model frame; orientations are 3x3 matrices of
the moving object's pose in that frame. Screw order is ``[s0 (rotation), s1 (translation)]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional, Sequence, Tuple

import numpy as np
from stereo_manip_tools.transforms import (
    quaternion_from_matrix, rotation_about_axis, rotation_log, skew)

from .contact_relation import (
    ContactEvaluator, ContactGeometry, ContactPair, EDGE, evaluate_contacts, FACE, VERTEX)
from .nonlinear_correction import constraint_rows
from .polyhedron import cross3, Polyhedron
from .small_linalg import svd

__all__ = [
    'ConstraintDirections',
    'OptimalResult',
    'constraint_matrix',
    'rotational_constraint',
    'rotational_constraint_rank',
    'constraint_directions',
    'held_point',
    'reference_translation',
    'scaled_singular_values',
    'optimal_orientation_rank2',
    'optimal_orientation_edge_on_face',
    'optimal_orientation_face_on_edge',
    'optimal_orientation_numerical',
    'classify_rank1',
    'optimal_translation',
    'correct_optimal',
]

RANK_TOLERANCE = 1e-6


@dataclass
class ConstraintDirections:
    """
    Orthonormal constrained / free directions of a contact relation (fixed frame).

    :ivar constrained_translation: shape (k, 3), span of the separating-plane normals.
    :ivar free_translation: shape (3 - k, 3), translations keeping every contact.
    :ivar constrained_rotation: shape (r, 3), rows spanning Eq. 3's ``g_i``.
    :ivar free_rotation: shape (3 - r, 3), rotation axes allowed by Eq. 3.
    :ivar rotation_rank: ``r``, rank of Eq. 3.
    :ivar constraint_rank: rank of Eq. 2 (0-6).
    """

    constrained_translation: np.ndarray
    free_translation: np.ndarray
    constrained_rotation: np.ndarray
    free_rotation: np.ndarray
    rotation_rank: int
    constraint_rank: int


@dataclass
class OptimalResult:
    """
    Outcome of :func:`correct_optimal`.

    :ivar T_rel: optimal pose of the moving object in the fixed frame (4x4).
    :ivar method: orientation rule used: 'rank0', 'rank2-eq5', 'rank1-eq8', 'rank1-eq9',
        'rank1-numerical', 'rank3'.
    :ivar directions: constraint directions at the non-linear solution.
    :ivar max_residual: largest |distance| of the relation at ``T_rel`` [m].
    :ivar orientation_change: rotation vector of ``Theta_opt Theta_E^T`` [rad], shape (3,).
    :ivar translation_change: ``t_opt - t_E`` [m], shape (3,).
    """

    T_rel: np.ndarray
    method: str
    directions: ConstraintDirections
    max_residual: float
    orientation_change: np.ndarray = field(default_factory=lambda: np.zeros(3))
    translation_change: np.ndarray = field(default_factory=lambda: np.zeros(3))


def constraint_matrix(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                      pairs: Sequence[ContactPair]) -> Tuple[np.ndarray, ContactGeometry]:
    """
    Eq. 2 at pose ``T_rel``: one row ``[p_i x f_ij, f_ij]`` per contact / separating plane.

    :returns: ``A`` of shape (K, 6) (screw order ``[s0, s1]``) and the contact geometry.
    """
    g = evaluate_contacts(moving, fixed, T_rel, pairs)
    return constraint_rows(g.points, g.normals), g


def _orth_split(M: np.ndarray, tol: float) -> Tuple[np.ndarray, np.ndarray]:
    """Orthonormal bases (rows) of the row space and of the null space of ``M`` (., 3)."""
    if M.size == 0:
        return np.zeros((0, 3)), np.eye(3)
    _, s, Vt = svd(M)
    r = int(np.sum(s > tol * max(1.0, s[0] if len(s) else 1.0)))
    return Vt[:r], Vt[r:]


def rotational_constraint(A: np.ndarray, length_scale: float = 1.0,
                          tol: float = RANK_TOLERANCE) -> np.ndarray:
    """
    Rows ``g_i`` of Eq. 3 (orthonormal), shape (r, 3).

    ``s0`` is feasible iff ``A0 s0 = -A1 s1`` for some ``s1``, i.e. iff the component of
    ``A0 s0`` outside the range of ``A1`` vanishes: ``g`` spans the rows of ``(I - P1) A0``
    with ``P1`` the orthogonal projector onto ``range(A1)``.

    :param A: Eq. 2 matrix, shape (K, 6).
    :param length_scale: length [m] normalising the rotation columns for the rank test.
    """
    A = np.asarray(A, dtype=float).reshape(-1, 6)
    if len(A) == 0:
        return np.zeros((0, 3))
    A0, A1 = A[:, :3] / length_scale, A[:, 3:]
    U, s, _ = svd(A1, full_matrices=False)
    U1 = U[:, s > tol]
    G = A0 - U1 @ (U1.T @ A0)
    g, _ = _orth_split(G, tol)
    return g


def rotational_constraint_rank(A: np.ndarray, length_scale: float = 1.0,
                               tol: float = RANK_TOLERANCE) -> int:
    """Rank (0-3) of the rotational constraint of Eq. 3 for the Eq. 2 matrix ``A``."""
    return len(rotational_constraint(A, length_scale, tol))


def scaled_singular_values(A: np.ndarray, length_scale: float = 1.0) -> np.ndarray:
    """Singular values of Eq. 2's matrix ``A`` (K, 6), rotation columns / ``length_scale``."""
    A = np.asarray(A, dtype=float).reshape(-1, 6)
    return svd(np.hstack([A[:, :3] / length_scale, A[:, 3:]]), compute_uv=False)


def constraint_directions(A: np.ndarray, length_scale: float = 1.0,
                          tol: float = RANK_TOLERANCE,
                          singular_values: Optional[np.ndarray] = None
                          ) -> ConstraintDirections:
    """
    Constrained and free translation directions and rotation axes of Eq. 2's matrix ``A``.

    :param singular_values: ``scaled_singular_values(A, length_scale)`` when the caller has
        them already (the same values; not computed again).
    """
    A = np.asarray(A, dtype=float).reshape(-1, 6)
    ct, ft = _orth_split(A[:, 3:], tol)
    g = rotational_constraint(A, length_scale, tol)
    _, fr = _orth_split(g, tol) if len(g) else (None, np.eye(3))
    if len(A):
        s = scaled_singular_values(A, length_scale) if singular_values is None \
            else singular_values
        crank = int(np.sum(s > tol * max(1.0, s[0])))
    else:
        crank = 0
    return ConstraintDirections(ct, ft, g, fr, len(g), crank)


def optimal_orientation_rank2(R_E: np.ndarray, R_S: np.ndarray,
                              free_axis: np.ndarray) -> np.ndarray:
    """
    Eqs. 4-5: optimal orientation when one rotation axis (``free_axis``) is unconstrained.

    Solves ``R(m, alpha) R_E = R_a(beta) R_S`` with ``m`` perpendicular to the free axis ``a``
    (a swing-twist split of ``R_S R_E^T``) and returns ``R(m, alpha) R_E``: the non-linear
    orientation with its redundant rotation ``beta`` about ``a`` removed.
    """
    a = np.asarray(free_axis, dtype=float)
    a = a / np.linalg.norm(a)
    q = quaternion_from_matrix(R_S @ R_E.T)              # (x, y, z, w), w >= 0
    half = np.arctan2(-(q[:3] @ a), q[3])
    beta = 2.0 * half
    return rotation_about_axis(a, beta) @ R_S


def _tait_bryan(Q: np.ndarray, B: np.ndarray) -> np.ndarray:
    """
    Tait-Bryan angles of ``Q`` about the columns of an orthonormal basis.

    Angles (a1, a2, a3) with ``Q = R_b1(a1) R_b2(a2) R_b3(a3)`` for the right-handed
    orthonormal basis ``B = [b1, b2, b3]`` (columns).
    """
    M = B.T @ Q @ B     # = Rx(a1) Ry(a2) Rz(a3) in the basis B
    a2 = np.arcsin(np.clip(M[0, 2], -1.0, 1.0))
    return np.array([np.arctan2(-M[1, 2], M[2, 2]), a2, np.arctan2(-M[0, 1], M[0, 0])])


def _unit_normal_and_edge(face_normal: np.ndarray, edge_direction: np.ndarray
                          ) -> Tuple[np.ndarray, np.ndarray]:
    """Make a unit face normal ``n`` and a unit edge direction ``l`` exactly orthogonal to it."""
    n = np.asarray(face_normal, dtype=float)
    n = n / np.linalg.norm(n)
    el = np.asarray(edge_direction, dtype=float)
    el = el - (el @ n) * n
    return n, el / np.linalg.norm(el)


def optimal_orientation_edge_on_face(R_E: np.ndarray, R_S: np.ndarray, face_normal: np.ndarray,
                                     edge_direction: np.ndarray
                                     ) -> Tuple[np.ndarray, Tuple[float, float, float]]:
    """
    Eqs. 6-8 (case 1: an edge of the moving object on a face of the fixed object).

    ``R_m(beta, gamma) = R(n, gamma) R(l, beta)`` keeps the edge (direction ``l``) on the face
    (normal ``n``); the constrained axis is ``c = n x l``. Solves
    ``R_c(alpha) R_E = R(n, gamma) R(l, beta) R_S`` and returns ``R_c(alpha) R_E``.

    :param face_normal: ``n`` at the non-linear solution, fixed frame.
    :param edge_direction: ``l`` of the moving edge at the non-linear solution (``l . n = 0``).
    :returns: the optimal orientation and ``(alpha, beta, gamma)`` [rad].
    """
    n, el = _unit_normal_and_edge(face_normal, edge_direction)
    c = cross3(n, el)
    # R_E R_S^T = R_c(-alpha) R_n(gamma) R_l(beta)
    a1, gamma, beta = _tait_bryan(R_E @ R_S.T, np.column_stack([c, n, el]))
    alpha = -a1
    return rotation_about_axis(c, alpha) @ R_E, (float(alpha), float(beta), float(gamma))


def optimal_orientation_face_on_edge(R_E: np.ndarray, R_S: np.ndarray, face_normal: np.ndarray,
                                     edge_direction: np.ndarray
                                     ) -> Tuple[np.ndarray, Tuple[float, float, float]]:
    """
    Eqs. 6, 7, 9 (case 2: a face of the moving object on an edge of the fixed object).

    ``R_m(beta, gamma) = R(l, gamma) R(n, beta)`` keeps the face (normal ``n``) on the fixed
    edge (direction ``l``); the constrained axis is ``c = l x n``. Solves
    ``R_c(alpha) R_E = R(l, gamma) R(n, beta) R_S`` and returns ``R_c(alpha) R_E``.

    :returns: the optimal orientation and ``(alpha, beta, gamma)`` [rad].
    """
    n, el = _unit_normal_and_edge(face_normal, edge_direction)
    c = cross3(el, n)
    # R_E R_S^T = R_c(-alpha) R_l(gamma) R_n(beta)
    a1, gamma, beta = _tait_bryan(R_E @ R_S.T, np.column_stack([c, el, n]))
    alpha = -a1
    return rotation_about_axis(c, alpha) @ R_E, (float(alpha), float(beta), float(gamma))


def _left_jacobian(phi: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(phi))
    K = skew(phi)
    if th < 1e-8:
        return np.eye(3) + 0.5 * K
    return (np.eye(3) + (1.0 - np.cos(th)) / th**2 * K
            + (th - np.sin(th)) / th**3 * (K @ K))


def optimal_orientation_numerical(moving: Polyhedron, fixed: Polyhedron, T_rel_E: np.ndarray,
                                  T_rel_S: np.ndarray, pairs: Sequence[ContactPair],
                                  constrained_axes: np.ndarray, max_iterations: int = 50,
                                  residual_tolerance: float = 1e-11
                                  ) -> Tuple[np.ndarray, float]:
    """
    General optimal orientation for any rank: ``Theta_opt = exp([C^T alpha]x) Theta_E``.

    Generalises Eqs. 5 and 7: the optimum differs from the observation only by a rotation
    whose axis lies in the constrained subspace ``C`` (rows: Eq. 3's ``g_i``), and it must
    admit a translation satisfying every contact. Solves for ``alpha`` (r unknowns) and the
    translation by Gauss-Newton on the contact distances, started from the projection of the
    non-linear correction's rotation onto ``C``. Used for rank-1 relations that are neither
    Eq. 8 nor Eq. 9 (e.g. two vertices on two different faces); gives the same result as
    Eqs. 5, 8 and 9 where those apply.

    :returns: the optimal orientation (3x3) and the largest |distance| reached [m].
    """
    C = np.asarray(constrained_axes, dtype=float).reshape(-1, 3)
    R_E = T_rel_E[:3, :3]
    if len(C) == 0:
        return R_E.copy(), float('nan')
    L = max(moving.size, 1e-6)
    alpha = C @ rotation_log(T_rel_S[:3, :3] @ R_E.T)
    t = T_rel_S[:3, 3].copy()
    best = (None, np.inf)
    evaluate = ContactEvaluator(moving, fixed, pairs)
    for _ in range(max_iterations):
        phi = C.T @ alpha
        ang = float(np.linalg.norm(phi))
        R = (rotation_about_axis(phi, ang) if ang > 0 else np.eye(3)) @ R_E
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        g = evaluate(T)
        res = float(np.max(np.abs(g.distances)))
        if res < best[1]:
            best = (R, res)
        if res <= residual_tolerance:
            break
        # rotation acts on the body part p - t only (t is a separate unknown)
        Jrot = cross3(g.points - t, g.normals) @ (_left_jacobian(phi) @ C.T)
        J = np.hstack([Jrot / L, g.normals])
        step, *_ = np.linalg.lstsq(J, -g.distances, rcond=1e-10)
        alpha = alpha + step[:len(C)] / L
        t = t + step[len(C):]
    return best[0], best[1]


def _line_fit(points: np.ndarray, tol: float) -> Optional[Tuple[np.ndarray, np.ndarray]]:
    """(point, unit direction) of the line through ``points`` if they are collinear."""
    c = points.mean(0)
    _, s, Vt = svd(points - c)
    if len(points) < 2 or s[0] < tol or (len(s) > 1 and s[1] > tol):
        return None
    return c, Vt[0]


def classify_rank1(moving: Polyhedron, fixed: Polyhedron, T_rel_S: np.ndarray,
                   geometry: ContactGeometry, pairs: Sequence[ContactPair],
                   tol: float = 1e-7) -> Tuple[str, Optional[int], Optional[int]]:
    """
    Which of the chapter's rank-1 cases a relation is, at the non-linear solution.

    Both cases have every separating plane equal (normal ``n``) and the contact points on one
    line (direction ``l``). Case 1 (Eq. 8) when that line is an edge of the moving object lying
    on a face of the fixed object; case 2 (Eq. 9) when it is an edge of the fixed object lying
    on a face of the moving object.

    :returns: ('eq8', fixed face, moving edge) | ('eq9', moving face, fixed edge) |
        ('other', None, None).
    """
    N, P = geometry.normals, geometry.points
    if len(N) < 2 or np.any(np.linalg.norm(cross3(N, N[0]), axis=1) > 1e-6):
        return 'other', None, None
    line = _line_fit(P, tol * 10 + 1e-9)
    if line is None:
        return 'other', None, None
    c, el = line
    n = N[0]
    R, t = T_rel_S[:3, :3], T_rel_S[:3, 3]

    def edge_on_line(A: np.ndarray, D: np.ndarray) -> Optional[int]:
        ok = (np.linalg.norm(cross3(D, el), axis=1) < 1e-6) \
            & (np.linalg.norm(cross3(c - A, el), axis=1) < 1e-6)
        return int(np.flatnonzero(ok)[0]) if np.any(ok) else None

    kinds = {(p.moving_type, p.fixed_type) for p in pairs}
    if kinds <= {(VERTEX, FACE), (EDGE, EDGE)}:
        faces = np.flatnonzero((fixed.face_normals @ n > 1 - 1e-9)
                               & (np.abs(fixed.face_offsets - fixed.face_normals @ c) < 1e-6))
        if len(faces):
            e = edge_on_line(moving.vertices[moving.edge_vertices[:, 0]] @ R.T + t,
                             moving.edge_directions @ R.T)
            if e is not None:
                return 'eq8', int(faces[0]), e
    if kinds <= {(FACE, VERTEX), (EDGE, EDGE)}:
        nm = moving.face_normals @ R.T
        off = moving.face_offsets + nm @ t
        faces = np.flatnonzero((nm @ n < -1 + 1e-9) & (np.abs(off - nm @ c) < 1e-6))
        if len(faces):
            e = edge_on_line(fixed.vertices[fixed.edge_vertices[:, 0]], fixed.edge_directions)
            if e is not None:
                return 'eq9', int(faces[0]), e
    return 'other', None, None


def held_point(T_rel: np.ndarray, reference_point: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return where a point of the moving object is at the relative pose ``T_rel`` (4x4).

    :param reference_point: (3,) [m, moving frame] (``correct_pose``'s); None: the origin.
    :return: (3,) [m, fixed frame].
    """
    T = np.asarray(T_rel, dtype=float)
    if reference_point is None:
        return T[:3, 3].copy()
    return T[:3, :3] @ np.asarray(reference_point, dtype=float).reshape(3) + T[:3, 3]


def reference_translation(T_rel_E: np.ndarray, R: np.ndarray,
                          reference_point: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Return the translation that keeps a point of the moving object where it was observed.

    The translation rule of step 4 changes the observed translation by the least amount; which
    translation is "observed" once the orientation has changed from ``Theta_E`` to ``R`` depends
    on the point of the moving object held fixed: the model's origin (the chapter's reading,
    ``t_E``) or any ``reference_point`` ``c``: ``t_E + (Theta_E - R) c``. The origin of a
    model is arbitrary (a CAD convention); with ``c`` the surface centroid the rule moves the
    model's points least on average (the mean squared displacement of the points under a
    rotation change plus a translation is least when the centroid's displacement is), and a
    correction that removes a tilt about the centroid leaves the centroid in place. Measured
    on the demo's peg (origin at its bottom face, 120 mm tall), whose localised poses tilt
    about a point 60-90 mm up: see ``correct_pose``'s ``reference_point``.

    :param T_rel_E: observed pose of the moving object in the fixed frame (4x4).
    :param R: the corrected orientation (3x3).
    :param reference_point: (3,) [m, moving frame]; None: the origin (``t_E`` returned).
    """
    if reference_point is None:
        return held_point(T_rel_E)
    return held_point(T_rel_E, reference_point) - np.asarray(R, dtype=float) @ np.asarray(
        reference_point, dtype=float).reshape(3)


def optimal_translation(moving: Polyhedron, fixed: Polyhedron, R_opt: np.ndarray,
                        t_observed: np.ndarray, pairs: Sequence[ContactPair],
                        tol: float = RANK_TOLERANCE, free_directions: bool = True
                        ) -> Tuple[np.ndarray, float, Optional[np.ndarray]]:
    """
    Least-squares translation restricted to the contact constraints.

    With the orientation fixed, ``d_i(t) = f_i . (t - t_E) + d_i(t_E)``; the minimum-norm
    solution ``t = t_E - F^+ d(t_E)`` changes ``t_E`` only within ``span{f_i}`` so the
    component along every free translation direction is exactly the observed one.

    :param free_directions: also return the free translation directions (False: None in
        their place, one SVD less).
    :returns: the translation [m] (3,), the largest |distance| there [m], and the free
        translation directions (rows).
    """
    t_E = np.asarray(t_observed, dtype=float).reshape(3)
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_opt, t_E
    evaluate = ContactEvaluator(moving, fixed, pairs)
    g = evaluate(T)
    F = g.normals
    U, s, Vt = svd(F, full_matrices=False)
    keep = s > tol * max(1.0, s[0])
    # pseudo-inverse restricted to the well-determined directions
    dt = -(Vt[keep].T @ ((U[:, keep].T @ g.distances) / s[keep]))
    t = t_E + dt
    T[:3, 3] = t
    res = float(np.max(np.abs(evaluate(T).distances)))
    return t, res, _orth_split(F, tol)[1] if free_directions else None


def _orientation_rule(moving: Polyhedron, fixed: Polyhedron, T_rel_E: np.ndarray,
                      T_rel_S: np.ndarray, pairs: Sequence[ContactPair], rank1_method: str,
                      case: Optional[Tuple[str, Optional[int], Optional[int]]] = None
                      ) -> Tuple[np.ndarray, str, ConstraintDirections, tuple]:
    L = max(moving.size, 1e-6)
    A, geom = constraint_matrix(moving, fixed, T_rel_S, pairs)
    dirs = constraint_directions(A, L)
    R_E, R_S = T_rel_E[:3, :3], T_rel_S[:3, :3]
    r = dirs.rotation_rank
    if r == 3:
        return R_S.copy(), 'rank3', dirs, case
    if r == 0:
        return R_E.copy(), 'rank0', dirs, case
    if r == 2:
        return (optimal_orientation_rank2(R_E, R_S, dirs.free_rotation[0]), 'rank2-eq5', dirs,
                case)
    if case is None:
        case = ('other', None, None)
        if rank1_method == 'auto':
            case = classify_rank1(moving, fixed, T_rel_S, geom, pairs)
    kind, a, b = case
    if kind == 'eq8':      # a: fixed face, b: moving edge
        n, el = fixed.face_normals[a], R_S @ moving.edge_directions[b]
        return optimal_orientation_edge_on_face(R_E, R_S, n, el)[0], 'rank1-eq8', dirs, case
    if kind == 'eq9':      # a: moving face, b: fixed edge
        n, el = R_S @ moving.face_normals[a], fixed.edge_directions[b]
        return optimal_orientation_face_on_edge(R_E, R_S, n, el)[0], 'rank1-eq9', dirs, case
    R_opt, _ = optimal_orientation_numerical(moving, fixed, T_rel_E, T_rel_S, pairs,
                                             dirs.constrained_rotation)
    return R_opt, 'rank1-numerical', dirs, case


def correct_optimal(moving: Polyhedron, fixed: Polyhedron, T_rel_E: np.ndarray,
                    T_rel_S: np.ndarray, pairs: Sequence[ContactPair],
                    rank1_method: str = 'auto', refine: int = 5,
                    residual_tolerance: float = 1e-9,
                    reference_point: Optional[np.ndarray] = None) -> OptimalResult:
    """
    Optimal correction from the observed pose ``T_rel_E`` and a feasible pose ``T_rel_S``.

    The frame A of Eqs. 4-7 is taken from Eq. 3 at ``T_rel_S``. Where the free axes depend on
    the orientation (rank 1, and rank 2 in general) the result is refined by a fixed-point
    iteration that re-applies the rule with ``T_rel_S`` replaced by the last optimum, until the
    rotation from ``Theta_E`` to ``Theta_opt`` is about the constrained axes *of the optimum
    itself* (at most ``refine`` extra rounds; at the fixed point Eq. 4/6's beta, gamma are 0).

    :param T_rel_E: observed pose of the moving object in the fixed frame (4x4).
    :param T_rel_S: pose satisfying the relation (non-linear step), 4x4.
    :param pairs: the contact relation.
    :param rank1_method: 'auto' (Eq. 8 / Eq. 9 when they apply, else numerical) or
        'numerical' (always the general method).
    :param refine: extra fixed-point rounds (0 = the chapter's single application).
    :param residual_tolerance: a refinement round is kept only if its contact residual is
        below this [m].
    :param reference_point: (3,) the point of the moving object [m, moving frame] whose
        observed position the translation rule keeps along every free direction
        (:func:`reference_translation`); None: the moving origin, as the chapter.
    """
    R_E = T_rel_E[:3, :3]
    S = np.array(T_rel_S, dtype=float)
    best: Optional[Tuple[np.ndarray, str, ConstraintDirections, float]] = None
    case = None
    for k in range(refine + 1):
        R_opt, method, dirs, case = _orientation_rule(moving, fixed, T_rel_E, S, pairs,
                                                      rank1_method, case)
        t_opt, res, _ = optimal_translation(
            moving, fixed, R_opt, reference_translation(T_rel_E, R_opt, reference_point),
            pairs, free_directions=False)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_opt, t_opt
        if best is not None and res > max(residual_tolerance, best[3]):
            break
        change = 0.0 if best is None else float(np.linalg.norm(
            rotation_log(R_opt @ best[0][:3, :3].T)))
        best = (T, method, dirs, res)
        if dirs.rotation_rank in (0, 3) or (change < 1e-13 and k > 0):
            break
        S = T
    T, method, dirs, res = best
    return OptimalResult(T, method, dirs, res, rotation_log(T[:3, :3] @ R_E.T),
                         T[:3, 3] - T_rel_E[:3, 3])
