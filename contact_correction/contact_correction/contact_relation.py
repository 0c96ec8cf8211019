"""
Contact relation between a moving and a fixed polyhedron (Section 3; Hirukawa et al. 1994).

A contact relation is the set of pairs of contacting elements. Following Hirukawa et al. the
elementary pairs are vertex-face (a vertex of the moving object on a face of the fixed one),
face-vertex (a vertex of the fixed object on a face of the moving one) and edge-edge (two
non-parallel edges crossing); edge-face and face-face contacts are represented by their
vertex-face, face-vertex and edge-edge combinations (an edge lying on a face gives its end
vertices on the face plus its crossings with the face's boundary edges).

Everything is computed in the **fixed object's model frame**: the relative pose
``T_rel = inv(T_fixed) @ T_moving`` maps moving-model points into it. Each pair has a contact
point ``p`` and the unit normal ``f`` of its separating plane, pointing from the fixed object
towards the moving one, and a signed distance ``d`` (> 0 apart, < 0 interpenetrating) whose
first-order change under an infinitesimal screw ``[s0, s1]`` of the moving object (rotation
``s0`` [rad], translation ``s1`` [m] of the frame origin) is ``f . s1 + (p x f) . s0`` --
exactly the row of Eq. 2.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from typing import List, Optional, Sequence, Tuple

import numpy as np
from stereo_manip_tools.transforms import invert_transform, transform_points

from .polyhedron import cross3, Polyhedron

__all__ = [
    'VERTEX',
    'EDGE',
    'FACE',
    'ContactPair',
    'ContactGeometry',
    'detect_contact_relation',
    'evaluate_contacts',
    'ContactEvaluator',
    'penetration_depth',
    'off_element_distance',
    'relative_pose',
    'pair_key',
    'parse_relation',
]

VERTEX = 0
EDGE = 1
FACE = 2
_TYPE_NAME = {VERTEX: 'vertex', EDGE: 'edge', FACE: 'face'}


@dataclass(frozen=True)
class ContactPair:
    """
    One pair of contacting elements.

    :ivar moving_type: VERTEX, EDGE or FACE on the moving object.
    :ivar moving_index: element index on the moving polyhedron.
    :ivar fixed_type: element type on the fixed object.
    :ivar fixed_index: element index on the fixed polyhedron.
    :ivar sign: for edge-edge pairs, +1/-1 orienting ``e_moving x e_fixed`` from the fixed to
        the moving object (ignored for the other kinds).
    """

    moving_type: int
    moving_index: int
    fixed_type: int
    fixed_index: int
    sign: int = 1

    @property
    def kind(self) -> str:
        """'vertex-face', 'face-vertex' or 'edge-edge'."""
        return f'{_TYPE_NAME[self.moving_type]}-{_TYPE_NAME[self.fixed_type]}'

    def __str__(self) -> str:
        return (f'{_TYPE_NAME[self.moving_type]} {self.moving_index} - '
                f'{_TYPE_NAME[self.fixed_type]} {self.fixed_index}')


_TYPE_CODE = {'vertex': VERTEX, 'edge': EDGE, 'face': FACE}


def parse_relation(text: str) -> List[ContactPair]:
    """
    Parse a contact relation from text.

    Contact relation from text: pairs separated by ';' or new lines, each written as
    :class:`ContactPair` prints it, ``'vertex 3 - face 1'``, ``'face 2 - vertex 7'`` or
    ``'edge 4 - edge 9'`` (moving element first; edge-edge may end with ``' -'`` for the
    negative sign).

    :raises ValueError: naming the malformed entry.
    """
    pairs: List[ContactPair] = []
    for item in text.replace('\n', ';').split(';'):
        item = item.strip()
        if not item:
            continue
        sign = 1
        if item.endswith(' -'):
            sign, item = -1, item[:-2].strip()
        parts = [p.split() for p in item.split('-')]
        if len(parts) != 2 or any(len(p) != 2 for p in parts):
            raise ValueError(f"relation entry {item!r}: expected '<type> <index> - <type> "
                             "<index>', e.g. 'vertex 3 - face 1'")
        try:
            (mt, mi), (ft, fi) = [(_TYPE_CODE[t.lower()], int(i)) for t, i in parts]
        except (KeyError, ValueError):
            raise ValueError(f'relation entry {item!r}: types are vertex, edge, face and '
                             'indices integers') from None
        if (mt, ft) not in ((VERTEX, FACE), (FACE, VERTEX), (EDGE, EDGE)):
            raise ValueError(f'relation entry {item!r}: use vertex-face, face-vertex or '
                             'edge-edge')
        if mi < 0 or fi < 0:
            raise ValueError(f'relation entry {item!r}: negative index')
        pairs.append(ContactPair(mt, mi, ft, fi, sign))
    return pairs


def pair_key(pair: ContactPair) -> Tuple[int, int, int, int]:
    """Identity of a pair for set comparisons (ignores the edge-edge sign)."""
    return (pair.moving_type, pair.moving_index, pair.fixed_type, pair.fixed_index)


@dataclass
class ContactGeometry:
    """
    Geometry of a contact relation at one pose, fixed-object frame.

    :ivar distances: signed distances [m], shape (K,).
    :ivar points: contact points [m], shape (K, 3).
    :ivar normals: separating-plane unit normals f (fixed -> moving), shape (K, 3).
    """

    distances: np.ndarray
    points: np.ndarray
    normals: np.ndarray


def relative_pose(T_moving: np.ndarray, T_fixed: np.ndarray) -> np.ndarray:
    """Pose of the moving object in the fixed object's model frame, 4x4."""
    return invert_transform(T_fixed) @ np.asarray(T_moving, dtype=float)


@lru_cache(maxsize=256)
def _split_pairs(pairs: Tuple[ContactPair, ...]) -> tuple:
    """Index arrays of a relation by kind (cached: a relation is evaluated many times)."""
    vf = [k for k, p in enumerate(pairs) if p.moving_type == VERTEX and p.fixed_type == FACE]
    fv = [k for k, p in enumerate(pairs) if p.moving_type == FACE and p.fixed_type == VERTEX]
    ee = [k for k, p in enumerate(pairs) if p.moving_type == EDGE and p.fixed_type == EDGE]
    if len(vf) + len(fv) + len(ee) != len(pairs):
        bad = next(p for p in pairs if (p.moving_type, p.fixed_type) not in
                   ((VERTEX, FACE), (FACE, VERTEX), (EDGE, EDGE)))
        raise ValueError(f'unsupported contact pair kind {bad.kind!r} ({bad}); use '
                         'vertex-face, face-vertex or edge-edge')

    def idx(ks: List[int], attr: str) -> np.ndarray:
        return np.array([getattr(pairs[k], attr) for k in ks], dtype=np.int64)

    return (np.array(vf, dtype=np.int64), idx(vf, 'moving_index'), idx(vf, 'fixed_index'),
            np.array(fv, dtype=np.int64), idx(fv, 'moving_index'), idx(fv, 'fixed_index'),
            np.array(ee, dtype=np.int64), idx(ee, 'moving_index'), idx(ee, 'fixed_index'),
            idx(ee, 'sign').astype(float))


def evaluate_contacts(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                      pairs: Sequence[ContactPair]) -> ContactGeometry:
    """
    Signed distances, contact points and separating-plane normals of ``pairs`` at ``T_rel``.

    :param T_rel: pose of the moving object in the fixed object's frame (4x4).
    :raises ValueError: on a pair kind other than vertex-face, face-vertex, edge-edge, or an
        edge-edge pair whose edges are parallel at this pose.
    """
    return ContactEvaluator(moving, fixed, pairs)(T_rel)


class ContactEvaluator:
    """
    :func:`evaluate_contacts` for one relation at many poses (the model data gathered once).

    ``ContactEvaluator(moving, fixed, pairs)(T_rel)`` equals
    ``evaluate_contacts(moving, fixed, T_rel, pairs)`` (the same arithmetic); an iterative
    solver evaluating one relation at each iterate saves the per-call splitting and gathering.

    :raises ValueError: on a pair kind other than vertex-face, face-vertex, edge-edge.
    """

    def __init__(self, moving: Polyhedron, fixed: Polyhedron,
                 pairs: Sequence[ContactPair]) -> None:
        """Split ``pairs`` by kind and gather their model data (model frames)."""
        self.pairs = tuple(pairs)
        vf, vi, fi, fv, fi2, wi, ee, mi, ei, sg = _split_pairs(self.pairs)
        self.vf, self.fv, self.ee, self.sg = vf, fv, ee, sg
        if len(vf):
            self.vf_x = moving.vertices[vi]
            self.vf_n = fixed.face_normals[fi]
            self.vf_off = fixed.face_offsets[fi]
        if len(fv):
            self.fv_w = fixed.vertices[wi]
            self.fv_n = moving.face_normals[fi2]
            self.fv_off = moving.face_offsets[fi2]
        if len(ee):
            self.ee_a = moving.vertices[moving.edge_vertices[mi, 0]]
            self.ee_em = moving.edge_directions[mi]
            self.ee_b = fixed.vertices[fixed.edge_vertices[ei, 0]]
            self.ee_ef = fixed.edge_directions[ei]

    def __call__(self, T_rel: np.ndarray) -> ContactGeometry:
        """Contact geometry at ``T_rel`` (4x4, moving object in the fixed frame)."""
        K = len(self.pairs)
        d = np.zeros(K)
        P = np.zeros((K, 3))
        N = np.zeros((K, 3))
        R, t = T_rel[:3, :3], T_rel[:3, 3]
        vf, fv, ee = self.vf, self.fv, self.ee
        if len(vf):
            x = self.vf_x @ R.T + t
            n = self.vf_n
            d[vf] = (n * x).sum(1) - self.vf_off
            P[vf], N[vf] = x, n
        if len(fv):
            w = self.fv_w
            nm = self.fv_n @ R.T
            off = self.fv_off + nm @ t          # moving face plane in the fixed frame
            d[fv] = (nm * w).sum(1) - off
            P[fv], N[fv] = w, -nm
        if len(ee):
            a = self.ee_a @ R.T + t
            em = self.ee_em @ R.T
            b = self.ee_b
            ef = self.ee_ef
            c = cross3(em, ef)
            s = np.linalg.norm(c, axis=1)
            if np.any(s < 1e-9):
                bad = self.pairs[ee[int(np.argmin(s))]]
                raise ValueError(f'edge-edge pair ({bad}) has parallel edges at this pose')
            n = self.sg[:, None] * c / s[:, None]
            w0 = a - b
            d[ee] = (n * w0).sum(1)
            B = (em * ef).sum(1)
            u = ((ef * w0).sum(1) - B * (em * w0).sum(1)) / (1.0 - B * B)
            P[ee], N[ee] = b + u[:, None] * ef, n
        return ContactGeometry(d, P, N)


def off_element_distance(moving: Polyhedron, fixed: Polyhedron, T_rel: np.ndarray,
                         pairs: Sequence[ContactPair]) -> np.ndarray:
    """
    How far [m] each pair's contact point lies outside its elements at ``T_rel``.

    Contact distances are measured to infinite planes and lines; a relation is only realised
    when every contact point also lies on its bounded elements: the vertex's projection on the
    face region (vertex-face, face-vertex), the crossing point on both edge segments
    (edge-edge). 0 when it does.

    :returns: shape (K,), >= 0.
    """
    out = np.zeros(len(pairs))
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    T_inv = invert_transform(T_rel)
    # projections gathered per solid, their face distances measured in one call each
    proj: Tuple[Tuple[list, list, list], Tuple[list, list, list]] = (([], [], []),
                                                                     ([], [], []))
    for k, p in enumerate(pairs):
        if p.moving_type == VERTEX and p.fixed_type == FACE:
            x = R @ moving.vertices[p.moving_index] + t
            n = fixed.face_normals[p.fixed_index]
            q = x - (n @ x - fixed.face_offsets[p.fixed_index]) * n
            for lst, v in zip(proj[0], (k, p.fixed_index, q)):
                lst.append(v)
        elif p.moving_type == FACE and p.fixed_type == VERTEX:
            w = T_inv[:3, :3] @ fixed.vertices[p.fixed_index] + T_inv[:3, 3]
            n = moving.face_normals[p.moving_index]
            q = w - (n @ w - moving.face_offsets[p.moving_index]) * n
            for lst, v in zip(proj[1], (k, p.moving_index, q)):
                lst.append(v)
        elif p.moving_type == EDGE and p.fixed_type == EDGE:
            a = R @ moving.vertices[moving.edge_vertices[p.moving_index, 0]] + t
            em = R @ moving.edge_directions[p.moving_index]
            b = fixed.vertices[fixed.edge_vertices[p.fixed_index, 0]]
            ef = fixed.edge_directions[p.fixed_index]
            w0 = a - b
            B = em @ ef
            den = max(1.0 - B * B, 1e-18)
            sm = (B * (ef @ w0) - em @ w0) / den
            sf = (ef @ w0 - B * (em @ w0)) / den
            Lm = moving.edge_lengths[p.moving_index]
            Lf = fixed.edge_lengths[p.fixed_index]
            out[k] = max(0.0, -sm, sm - Lm, -sf, sf - Lf)
    for (ks, faces, qs), solid in zip(proj, (fixed, moving)):
        if ks:
            out[ks] = solid.faces_distance(np.array(faces), np.array(qs))
    return out


def detect_contact_relation(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                            T_fixed: np.ndarray, tolerance: float = 1e-3,
                            penetration_tolerance: float | None = None,
                            angle_tolerance: float = 0.1) -> List[ContactPair]:
    """
    Detect the contact relation between the moving and the fixed object at the given poses.

    A pair is in contact when its signed distance lies in ``[-penetration_tolerance,
    tolerance]``, its contact point lies on both elements (within the same margin) and the
    separating plane locally separates the two solids: for a vertex, no incident edge may run
    into the other solid's interior (deeper than the tolerances allow); for an edge pair, both
    wedges must lie on their side of the plane within ``angle_tolerance``. Parallel edge pairs
    and edge crossings at an end vertex are left to the vertex-face / face-vertex pairs that
    represent them.

    :param T_moving: pose of the moving object (4x4) in a common frame.
    :param T_fixed: pose of the fixed object (4x4) in the same frame.
    :param tolerance: largest separation counted as contact [m].
    :param penetration_tolerance: largest interpenetration counted as contact [m] (default:
        ``tolerance``); deeper pairs are not part of the relation.
    :param angle_tolerance: slack [rad] of the local separation test.
    :returns: the pairs, ordered vertex-face, face-vertex, edge-edge, by element index.
    """
    if tolerance < 0:
        raise ValueError(f'tolerance must be >= 0, got {tolerance}')
    pen = tolerance if penetration_tolerance is None else float(penetration_tolerance)
    margin = max(tolerance, pen)
    sin_tol = np.sin(angle_tolerance)
    T_rel = relative_pose(T_moving, T_fixed)
    R, t = T_rel[:3, :3], T_rel[:3, 3]
    pairs: List[ContactPair] = []

    # vertex (moving) - face (fixed), in the fixed frame
    for v, f in _vertex_face_candidates(moving, fixed, R, t, tolerance, pen, margin, sin_tol):
        pairs.append(ContactPair(VERTEX, v, FACE, f))
    # face (moving) - vertex (fixed), in the moving frame
    T_inv = invert_transform(T_rel)
    for w, f in _vertex_face_candidates(fixed, moving, T_inv[:3, :3], T_inv[:3, 3], tolerance,
                                        pen, margin, sin_tol):
        pairs.append(ContactPair(FACE, f, VERTEX, w))

    # edge - edge (both convex, not parallel, crossing away from their end vertices)
    em_idx = np.flatnonzero(moving.edge_convex)
    ef_idx = np.flatnonzero(fixed.edge_convex)
    if len(em_idx) and len(ef_idx):
        A = moving.vertices[moving.edge_vertices[em_idx, 0]] @ R.T + t     # (Em, 3)
        Em = moving.edge_directions[em_idx] @ R.T
        Lm = moving.edge_lengths[em_idx]
        Bf = fixed.vertices[fixed.edge_vertices[ef_idx, 0]]
        Ef = fixed.edge_directions[ef_idx]
        Lf = fixed.edge_lengths[ef_idx]
        C = cross3(Em[:, None, :], Ef[None, :, :])                       # (Em, Ef, 3)
        S = np.linalg.norm(C, axis=-1)
        ok = S > sin_tol
        W0 = A[:, None, :] - Bf[None, :, :]
        Bd = Em @ Ef.T
        den = np.where(ok, 1.0 - Bd * Bd, 1.0)
        dw_m = np.einsum('ik,ijk->ij', Em, W0)
        dw_f = np.einsum('jk,ijk->ij', Ef, W0)
        sm = (Bd * dw_f - dw_m) / den       # parameter [m] on the moving edge
        sf = (dw_f - Bd * dw_m) / den       # parameter [m] on the fixed edge
        end = max(margin, 1e-9)
        ok &= (sm > end) & (sm < Lm[:, None] - end) & (sf > end) & (sf < Lf[None, :] - end)
        for i, j in np.argwhere(ok):
            c = C[i, j] / S[i, j]
            fe = int(ef_idx[j])
            me = int(em_idx[i])
            out_f = fixed.face_normals[fixed.edge_faces[fe]].sum(0)
            sign = 1 if c @ out_f > 0 else -1
            n = sign * c
            d = n @ W0[i, j]
            if d < -pen or d > tolerance:
                continue
            # the plane must separate the two wedges locally
            if np.any(fixed.edge_face_inward[fe] @ n > sin_tol):
                continue
            if np.any((moving.edge_face_inward[me] @ R.T) @ n < -sin_tol):
                continue
            pairs.append(ContactPair(EDGE, me, EDGE, fe, sign))
    return pairs


def _vertex_face_candidates(vpoly: Polyhedron, fpoly: Polyhedron, R: np.ndarray, t: np.ndarray,
                            tolerance: float, pen: float, margin: float, sin_tol: float
                            ) -> List[Tuple[int, int]]:
    """
    (vertex of ``vpoly``, face of ``fpoly``) pairs in contact.

    ``R, t`` map ``vpoly``'s frame into ``fpoly``'s.
    """
    cos_tol = np.sqrt(max(0.0, 1.0 - sin_tol * sin_tol))
    idx = vpoly.feature_vertices
    V = vpoly.vertices[idx] @ R.T + t
    near = fpoly.in_bbox(V, margin)
    if not np.any(near):
        return []
    idx, V = idx[near], V[near]
    D = V @ fpoly.face_normals.T - fpoly.face_offsets
    ci, cf = np.nonzero((D >= -pen) & (D <= tolerance))
    if len(ci) == 0:
        return []
    Q = V[ci] - D[ci, cf][:, None] * fpoly.face_normals[cf]
    ok = fpoly.faces_distance(cf, Q) <= margin
    out = []
    ks = np.flatnonzero(ok)
    vs, fs = idx[ci[ks]], cf[ks]
    # vectorised tests (the per-candidate ones below, for all candidates at once): the lowest
    # edge direction of each vertex along the face normal, and the lowest normal of the
    # vertex's faces along it; a candidate whose values lie clearly (by 1e-9) on one side of
    # the thresholds is decided here, the others take the exact per-candidate tests
    nf_all = fpoly.face_normals[fs]
    lo_e = _vertex_min(vpoly.vertex_edge_table(), vs, R, nf_all)
    lo_f = _vertex_min(vpoly.vertex_face_table(), vs, R, nf_all)
    band = 1e-9
    clear = lo_e > -sin_tol + band                      # no edge below the plane: contact
    below = lo_e < -sin_tol - band                      # an edge below the plane ...
    apart = below & (lo_f > -cos_tol + band)            # ... and no face against: not one
    # the exact per-candidate tests; the cone tests of all candidates that need one are made
    # in one batch (the same per-point queries)
    decided: List[Optional[bool]] = []
    cones: List[Tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for j, (v, f, c, a) in enumerate(zip(vs.tolist(), fs.tolist(), clear.tolist(),
                                         apart.tolist())):
        if c:
            decided.append(True)
            continue
        if a:
            decided.append(False)
            continue
        dirs = vpoly.vertex_edge_dirs[v] @ R.T
        nf = fpoly.face_normals[f]
        if np.any(dirs @ nf < -sin_tol):
            # An edge of the vertex runs below the face's plane, so the vertex is not locally
            # above the face. The pair is still a contact when the vertex belongs to a face of
            # its own solid lying against this one (opposite normals: a face-face contact, e.g.
            # the inner corner of a T on a shoulder) and no edge enters the other solid.
            # Otherwise the face's plane does not separate the solids there: e.g. a vertex
            # level with a flush, coplanar face beside a slot it slides in (same normals).
            against = np.any((vpoly.face_normals[vpoly.vertex_faces[v]] @ R.T) @ nf
                             < -cos_tol)
            if not against:
                decided.append(False)
                continue
            decided.append(None)
            cones.append((V[ci[ks[j]]], dirs, vpoly.vertex_edge_lengths[v]))
            continue
        decided.append(True)
    enters = _cones_enter(cones, fpoly, pen, sin_tol) if cones else []
    c = 0
    for v, f, ok_j in zip(vs.tolist(), fs.tolist(), decided):
        if ok_j is None:
            ok_j = not enters[c]
            c += 1
        if ok_j:
            out.append((v, f))
    return out


try:
    import numba

    @numba.njit(cache=True, fastmath=False)
    def _vertex_min_kernel(rows_all: np.ndarray, start: np.ndarray, vs: np.ndarray,
                           cnt: np.ndarray, R: np.ndarray,
                           normals: np.ndarray) -> np.ndarray:  # pragma: no cover
        """Compiled :func:`_vertex_min` (every vertex has rows)."""
        out = np.empty(len(vs))
        for j in range(len(vs)):
            m = np.inf
            s0 = start[vs[j]]
            for r in range(s0, s0 + cnt[j]):
                val = 0.0
                for i in range(3):
                    val += (R[i, 0] * rows_all[r, 0] + R[i, 1] * rows_all[r, 1]
                            + R[i, 2] * rows_all[r, 2]) * normals[j, i]
                if val < m:
                    m = val
            out[j] = m
        return out
except ImportError:  # pragma: no cover - numba is in the environment
    _vertex_min_kernel = None


def _vertex_min(table: Tuple[np.ndarray, np.ndarray, np.ndarray], vs: np.ndarray,
                R: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """
    Lowest component along ``normals[j]`` of vertex ``vs[j]``'s rows rotated by ``R``.

    Per candidate ``j``: min over the vertex's rows r (a flattened table) of
    ``(R r) . normals[j]``; nan when a vertex has no rows.
    """
    rows_all, start, count = table
    out = np.full(len(vs), np.nan)
    cnt = count[vs]
    if len(vs) == 0 or not np.all(cnt > 0):
        return out
    if _vertex_min_kernel is not None:
        # compiled (the products summed in another order: equal to ~1e-16, far inside the
        # 1e-9 band within which the caller takes the exact per-candidate test)
        return _vertex_min_kernel(rows_all, start, vs.astype(np.int64), cnt.astype(np.int64),
                                  np.ascontiguousarray(R, dtype=float),
                                  np.ascontiguousarray(normals, dtype=float))
    seg = np.cumsum(cnt) - cnt
    rows = np.repeat(start[vs], cnt) + (np.arange(int(cnt.sum())) - np.repeat(seg, cnt))
    vals = ((rows_all[rows] @ R.T) * np.repeat(normals, cnt, axis=0)).sum(1)
    return np.minimum.reduceat(vals, seg)


def _cones_enter(cones: Sequence[Tuple[np.ndarray, np.ndarray, np.ndarray]], other: Polyhedron,
                 depth: float, sin_tol: float) -> List[bool]:
    """
    Tell, per vertex, whether an edge leaving it runs into the interior of ``other``.

    A point a quarter along each edge (at most 10 mm) is tested; it must be inside ``other``
    deeper than the allowed ``depth`` plus the angular slack. Points on ``other``'s surface
    (an edge lying along a face of the other solid) do not count. All vertices' points are
    queried in one batch.

    :param cones: per vertex: apex [m] (3,), edge directions (k, 3), edge lengths [m] (k,).
    :returns: per vertex, True when an edge enters ``other``.
    """
    delta = np.concatenate([np.minimum(0.25 * ln, 0.01) for _, _, ln in cones])
    q = np.concatenate([a + np.minimum(0.25 * ln, 0.01)[:, None] * d for a, d, ln in cones])
    owner = np.repeat(np.arange(len(cones)), [len(ln) for _, _, ln in cones])
    hit = np.zeros(len(q), dtype=bool)
    box = np.flatnonzero(other.in_bbox(q))
    if len(box):
        inside = box[other.contains(q[box]) > 0.5 + 1e-3]
        if len(inside):
            dist = other.distance_to_surface(q[inside])
            hit[inside] = dist > depth + delta[inside] * sin_tol + 1e-9
    out = np.zeros(len(cones), dtype=bool)
    np.logical_or.at(out, owner, hit)
    return out.tolist()


def penetration_depth(moving: Polyhedron, fixed: Polyhedron, T_moving: np.ndarray,
                      T_fixed: np.ndarray, spacing: float = 0.005) -> float:
    """
    Largest interpenetration depth [m] between the two solids (0 when none).

    Vertices and points sampled every ``spacing`` [m] along the edges of each solid are tested
    for inclusion in the other (winding number); the depth of an included point is its distance
    to the other's surface. Edge-sampled, so an interpenetration thinner than ``spacing`` along
    an edge with no vertex inside can be underestimated.
    """
    T_rel = relative_pose(T_moving, T_fixed)
    T_inv = invert_transform(T_rel)
    depth = 0.0
    for pts, other in ((transform_points(T_rel, moving.edge_samples(spacing)), fixed),
                       (transform_points(T_inv, fixed.edge_samples(spacing)), moving)):
        depth = max(depth, other.penetration_of(pts, 0.5 + 1e-6))
    return depth
