"""
Polyhedral object models for contact reasoning (pure numpy; no rclpy).

A :class:`Polyhedron` is a closed, consistently oriented polygon mesh whose coplanar adjacent
polygons are merged into faces. It exposes the topological elements the contact relation of
Section 3 of the chapter is made of:

* vertices -- the input mesh vertices, indexed in file order (only *feature* vertices, i.e.
  vertices on at least one edge, take part in contacts);
* edges -- segments between two different (merged) faces, with their left face (the face that
  traverses the edge from ``edge_vertices[e, 0]`` to ``edge_vertices[e, 1]``), right face,
  and whether the edge is convex (dihedral angle inside the solid < 180 deg) or concave;
* faces -- planar regions with an outward unit normal ``n`` and offset ``d`` (``n . x = d`` on
  the face), stored as triangles so that non-convex faces and faces with holes (the top of a
  block with a through hole) are handled.

Non-convex solids work: every query is made against the triangles of the faces, never against
a convex-hull assumption. All coordinates are metres in the object's model frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np
from stereo_manip_tools.mesh_io import find_model, load_obj, PolygonMesh, surface_centroid
from stereo_manip_tools.transforms import perpendicular_basis

__all__ = [
    'Polyhedron',
    'load_polyhedron',
    'polyhedron_from_mesh',
    'point_triangle_distance',
    'min_triangle_distance',
    'cross3',
    'winding_number',
    'check_model_units',
]


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (broadcasting; cheaper than np.cross on small arrays)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (a * b).sum(-1)


def point_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """
    Euclidean distance from every point to every triangle.

    :param points: query points [m], shape (N, 3).
    :param tris: triangle corners [m], shape (M, 3, 3).
    :returns: distances [m], shape (N, M).
    """
    P = np.asarray(points, dtype=float).reshape(-1, 1, 3)
    A = tris[None, :, 0, :]
    B = tris[None, :, 1, :]
    C = tris[None, :, 2, :]
    ab = B - A
    ac = C - A
    n = cross3(ab, ac)
    nn = _dot(n, n)
    ap = P - A
    # barycentric coordinates of the projection onto the triangle plane
    with np.errstate(divide='ignore', invalid='ignore'):
        v = _dot(cross3(ap, ac), n) / nn
        w = _dot(cross3(ab, ap), n) / nn
        plane = np.abs(_dot(ap, n)) / np.sqrt(nn)
    inside = (v >= 0) & (w >= 0) & (v + w <= 1)

    def seg(p0: np.ndarray, d: np.ndarray) -> np.ndarray:
        dd = _dot(d, d)
        r = P - p0
        with np.errstate(divide='ignore', invalid='ignore'):
            s = np.clip(_dot(r, d) / dd, 0.0, 1.0)
        s = np.where(dd > 0, s, 0.0)
        q = r - s[..., None] * d
        return np.sqrt(_dot(q, q))

    edge = np.minimum(np.minimum(seg(A, ab), seg(B, C - B)), seg(C, A - C))
    return np.where(inside & np.isfinite(plane), plane, edge)


def winding_number(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """
    Generalised winding number of a closed outward-oriented triangle soup at each point.

    1 inside, 0 outside, 0.5 on a face (Van Oosterom-Strackee solid angles).

    :param points: query points [m], shape (N, 3).
    :param tris: triangle corners [m], shape (M, 3, 3), counter-clockwise from outside.
    :returns: winding numbers, shape (N,).
    """
    P = np.asarray(points, dtype=float).reshape(-1, 1, 3)
    a = tris[None, :, 0, :] - P
    b = tris[None, :, 1, :] - P
    c = tris[None, :, 2, :] - P
    la = np.sqrt(_dot(a, a))
    lb = np.sqrt(_dot(b, b))
    lc = np.sqrt(_dot(c, c))
    det = _dot(a, cross3(b, c))
    den = la * lb * lc + _dot(a, b) * lc + _dot(a, c) * lb + _dot(b, c) * la
    omega = 2.0 * np.arctan2(det, den)
    return omega.sum(axis=1) / (4.0 * np.pi)


try:  # compiled kernels for the per-frame queries; the numpy versions above are the fallback
    import numba

    @numba.njit(cache=True, fastmath=False, inline='always')
    def _tri_dist(px: float, py: float, pz: float, T: np.ndarray,
                  j: int) -> float:  # pragma: no cover
        """Distance from the point (px, py, pz) to triangle ``T[j]`` (3, 3)."""
        ax, ay, az = T[j, 0, 0], T[j, 0, 1], T[j, 0, 2]
        bx, by, bz = T[j, 1, 0], T[j, 1, 1], T[j, 1, 2]
        cx, cy, cz = T[j, 2, 0], T[j, 2, 1], T[j, 2, 2]
        abx, aby, abz = bx - ax, by - ay, bz - az
        acx, acy, acz = cx - ax, cy - ay, cz - az
        nx = aby * acz - abz * acy
        ny = abz * acx - abx * acz
        nz = abx * acy - aby * acx
        nn = nx * nx + ny * ny + nz * nz
        apx, apy, apz = px - ax, py - ay, pz - az
        d = np.inf
        if nn > 0.0:
            # barycentric (v, w) of the projection
            qx = apy * acz - apz * acy
            qy = apz * acx - apx * acz
            qz = apx * acy - apy * acx
            v = (qx * nx + qy * ny + qz * nz) / nn
            rx = aby * apz - abz * apy
            ry = abz * apx - abx * apz
            rz = abx * apy - aby * apx
            w = (rx * nx + ry * ny + rz * nz) / nn
            if v >= 0.0 and w >= 0.0 and v + w <= 1.0:
                d = abs(apx * nx + apy * ny + apz * nz) / np.sqrt(nn)
        if d == np.inf:
            for k in range(3):
                ox, oy, oz = T[j, k, 0], T[j, k, 1], T[j, k, 2]
                ex = T[j, (k + 1) % 3, 0] - ox
                ey = T[j, (k + 1) % 3, 1] - oy
                ez = T[j, (k + 1) % 3, 2] - oz
                ee = ex * ex + ey * ey + ez * ez
                sx, sy, sz = px - ox, py - oy, pz - oz
                u = 0.0
                if ee > 0.0:
                    u = (sx * ex + sy * ey + sz * ez) / ee
                    u = min(1.0, max(0.0, u))
                dx, dy, dz = sx - u * ex, sy - u * ey, sz - u * ez
                dd = np.sqrt(dx * dx + dy * dy + dz * dz)
                if dd < d:
                    d = dd
        return d

    @numba.njit(cache=True, fastmath=False)
    def _min_dist_kernel(P: np.ndarray, T: np.ndarray) -> np.ndarray:  # pragma: no cover
        n, m = P.shape[0], T.shape[0]
        out = np.empty(n)
        for i in range(n):
            best = np.inf
            for j in range(m):
                d = _tri_dist(P[i, 0], P[i, 1], P[i, 2], T, j)
                if d < best:
                    best = d
            out[i] = best
        return out

    @numba.njit(cache=True, fastmath=False)
    def _face_dist_kernel(P: np.ndarray, faces: np.ndarray, start: np.ndarray,
                          count: np.ndarray, tri_index: np.ndarray,
                          T: np.ndarray) -> np.ndarray:  # pragma: no cover
        """Distance from each point ``P[i]`` to the triangles of its face ``faces[i]``."""
        n = P.shape[0]
        out = np.empty(n)
        for i in range(n):
            best = np.inf
            f = faces[i]
            for r in range(start[f], start[f] + count[f]):
                d = _tri_dist(P[i, 0], P[i, 1], P[i, 2], T, tri_index[r])
                if d < best:
                    best = d
            out[i] = best
        return out

    @numba.njit(cache=True, fastmath=False, inline='always')
    def _winding_at(px: float, py: float, pz: float,
                    T: np.ndarray) -> float:  # pragma: no cover
        """Winding number of the triangles ``T`` (M, 3, 3) at the point (px, py, pz)."""
        acc = 0.0
        for j in range(T.shape[0]):
            ax, ay, az = T[j, 0, 0] - px, T[j, 0, 1] - py, T[j, 0, 2] - pz
            bx, by, bz = T[j, 1, 0] - px, T[j, 1, 1] - py, T[j, 1, 2] - pz
            cx, cy, cz = T[j, 2, 0] - px, T[j, 2, 1] - py, T[j, 2, 2] - pz
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            det = (ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz)
                   + az * (bx * cy - by * cx))
            den = (la * lb * lc + (ax * bx + ay * by + az * bz) * lc
                   + (ax * cx + ay * cy + az * cz) * lb + (bx * cx + by * cy + bz * cz) * la)
            acc += 2.0 * np.arctan2(det, den)
        return acc / (4.0 * np.pi)

    @numba.njit(cache=True, fastmath=False)
    def _winding_kernel(P: np.ndarray, T: np.ndarray) -> np.ndarray:  # pragma: no cover
        n = P.shape[0]
        out = np.empty(n)
        for i in range(n):
            out[i] = _winding_at(P[i, 0], P[i, 1], P[i, 2], T)
        return out

    @numba.njit(cache=True, fastmath=False)
    def _depth_kernel(P: np.ndarray, lo: np.ndarray, hi: np.ndarray, T: np.ndarray,
                      threshold: float) -> float:  # pragma: no cover
        """Deepest of the points inside the box and the surface ``T`` (winding > threshold)."""
        depth = 0.0
        for i in range(P.shape[0]):
            px, py, pz = P[i, 0], P[i, 1], P[i, 2]
            if not (lo[0] <= px <= hi[0] and lo[1] <= py <= hi[1] and lo[2] <= pz <= hi[2]):
                continue
            if _winding_at(px, py, pz, T) > threshold:
                best = np.inf
                for j in range(T.shape[0]):
                    d = _tri_dist(px, py, pz, T, j)
                    if d < best:
                        best = d
                if best > depth:
                    depth = best
        return depth

    _HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is in the environment; keep working without it
    _HAVE_NUMBA = False


def min_triangle_distance(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Distance [m] from each point (N, 3) to the nearest of the triangles (M, 3, 3), (N,)."""
    P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    if len(tris) == 0:
        return np.full(len(P), np.inf)
    if _HAVE_NUMBA:
        return _min_dist_kernel(P, np.ascontiguousarray(tris, dtype=float))
    return point_triangle_distance(P, tris).min(axis=1)


def _winding(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
    if _HAVE_NUMBA:
        return _winding_kernel(P, np.ascontiguousarray(tris, dtype=float))
    return winding_number(P, tris)


def _newell(p: np.ndarray) -> np.ndarray:
    q = np.roll(p, -1, axis=0)
    return np.array([
        np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
        np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
        np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
    ])


def _triangulate_polygon(V: np.ndarray, loop: np.ndarray, normal: np.ndarray) -> List[List[int]]:
    """Ear-clipping triangulation of a simple planar polygon (CCW about ``normal``)."""
    idx = [int(i) for i in loop]
    if len(idx) == 3:
        return [idx]
    u, w = perpendicular_basis(normal)   # 2D basis of the plane
    P2 = {i: np.array([V[i] @ u, V[i] @ w]) for i in idx}

    def cross2(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    tris: List[List[int]] = []
    ring = idx[:]
    guard = 0
    while len(ring) > 3 and guard < 10000:
        guard += 1
        m = len(ring)
        clipped = False
        for k in range(m):
            i0, i1, i2 = ring[k - 1], ring[k], ring[(k + 1) % m]
            a, b, c = P2[i0], P2[i1], P2[i2]
            if cross2(a, b, c) <= 1e-18:
                continue  # reflex or degenerate corner
            ok = True
            for j in ring:
                if j in (i0, i1, i2):
                    continue
                p = P2[j]
                if (cross2(a, b, p) >= 0 and cross2(b, c, p) >= 0 and cross2(c, a, p) >= 0):
                    ok = False
                    break
            if ok:
                tris.append([i0, i1, i2])
                ring.pop(k)
                clipped = True
                break
        if not clipped:
            raise ValueError('polygon face could not be triangulated (self-intersecting?)')
    tris.append(ring)
    return tris


def _flatten_rows(per_vertex: Dict[int, np.ndarray], n: int
                  ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stack per-vertex (k, 3) arrays into rows (M, 3), start (n,), count (n,) (0: absent)."""
    count = np.array([len(per_vertex.get(v, ())) for v in range(n)], dtype=np.int64)
    start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
    rows = [np.asarray(per_vertex[v], dtype=float).reshape(-1, 3) for v in range(n) if count[v]]
    return (np.vstack(rows) if rows else np.zeros((0, 3))), start, count


@dataclass
class Polyhedron:
    """
    A closed polyhedron with merged planar faces, edges and vertices (see module docstring).

    :ivar name: model name.
    :ivar vertices: vertex positions [m], shape (N, 3), model frame.
    :ivar triangles: vertex indices of the surface triangles, shape (T, 3), CCW from outside.
    :ivar triangle_face: merged-face index of each triangle, shape (T,).
    :ivar face_normals: outward unit normal per face, shape (F, 3).
    :ivar face_offsets: plane offset per face, ``n . x = d`` [m], shape (F,).
    :ivar edge_vertices: vertex indices of each edge, shape (E, 2).
    :ivar edge_faces: (left face, right face) of each edge, shape (E, 2); the left face
        traverses the edge from ``edge_vertices[e, 0]`` to ``edge_vertices[e, 1]``.
    :ivar edge_convex: True for convex edges, shape (E,).
    :ivar vertex_edges: for each vertex, the indices of the edges incident to it.

    Derived on construction, among others: ``size`` (bounding-box diagonal [m]) and
    ``centroid`` (area-weighted surface centroid [m], model frame).
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_face: np.ndarray
    face_normals: np.ndarray
    face_offsets: np.ndarray
    edge_vertices: np.ndarray
    edge_faces: np.ndarray
    edge_convex: np.ndarray
    vertex_edges: List[np.ndarray] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.tri_corners = self.vertices[self.triangles]          # (T, 3, 3)
        self.face_triangles = [np.flatnonzero(self.triangle_face == f)
                               for f in range(len(self.face_normals))]
        self._face_tris = [np.ascontiguousarray(self.tri_corners[t]) for t in self.face_triangles]
        self.feature_vertices = np.array(
            [i for i, e in enumerate(self.vertex_edges) if len(e) > 0], dtype=np.int64)
        ev = self.vertices[self.edge_vertices]                    # (E, 2, 3)
        self.edge_lengths = np.linalg.norm(ev[:, 1] - ev[:, 0], axis=1)
        self.edge_directions = (ev[:, 1] - ev[:, 0]) / self.edge_lengths[:, None]
        # unit vectors lying in each adjacent face, perpendicular to the edge, pointing into
        # the face (left face: n x d; right face traverses the edge backwards: n x -d)
        nl = self.face_normals[self.edge_faces[:, 0]]
        nr = self.face_normals[self.edge_faces[:, 1]]
        self.edge_face_inward = np.stack(
            [np.cross(nl, self.edge_directions), np.cross(nr, -self.edge_directions)], axis=1)
        self.vertex_edge_dirs: Dict[int, np.ndarray] = {}
        self.vertex_edge_lengths: Dict[int, np.ndarray] = {}
        for v, es in enumerate(self.vertex_edges):
            if len(es) == 0:
                continue
            dirs = []
            for e in es:
                a, b = self.edge_vertices[e]
                dirs.append(self.edge_directions[e] if a == v else -self.edge_directions[e])
            self.vertex_edge_dirs[v] = np.asarray(dirs)
            self.vertex_edge_lengths[v] = self.edge_lengths[es]
        # faces incident to each feature vertex (the faces of its edges)
        self.vertex_faces: Dict[int, np.ndarray] = {
            v: np.unique(self.edge_faces[es]) for v, es in enumerate(self.vertex_edges)
            if len(es) > 0}
        self.size = float(np.linalg.norm(self.vertices.max(0) - self.vertices.min(0)))
        #: area-weighted centroid of the surface [m], model frame
        self.centroid = surface_centroid(self.vertices, self.triangles)
        self.bbox_min = self.vertices.min(0)
        self.bbox_max = self.vertices.max(0)
        self._samples: Dict[float, np.ndarray] = {}
        self._vertex_edge_table: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None
        self._vertex_face_table: Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]] = None
        self._face_tri_table: Optional[tuple] = None

    def vertex_edge_table(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return ``vertex_edge_dirs`` flattened (cached): directions (M, 3), start, count (V,).

        Vertex ``v``'s edge directions are rows ``start[v]:start[v] + count[v]`` (count 0 for a
        vertex without edges).
        """
        if self._vertex_edge_table is None:
            self._vertex_edge_table = _flatten_rows(self.vertex_edge_dirs, len(self.vertices))
        return self._vertex_edge_table

    def vertex_face_table(self) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Return the normals of ``vertex_faces`` flattened (cached): (M, 3), start, count (V,).

        Vertex ``v``'s incident face normals are rows ``start[v]:start[v] + count[v]``.
        """
        if self._vertex_face_table is None:
            self._vertex_face_table = _flatten_rows(
                {v: self.face_normals[f] for v, f in self.vertex_faces.items()},
                len(self.vertices))
        return self._vertex_face_table

    def edge_samples(self, spacing: float) -> np.ndarray:
        """Feature vertices plus points every ``spacing`` [m] along each edge, (S, 3); cached."""
        key = float(spacing)
        if key not in self._samples:
            pts = [self.vertices[self.feature_vertices]]
            for e in range(self.n_edges):
                k = max(1, int(np.ceil(self.edge_lengths[e] / spacing)))
                s = (np.arange(1, k) / k)[:, None]
                a, b = self.vertices[self.edge_vertices[e]]
                pts.append(a + s * (b - a))
            self._samples[key] = np.vstack(pts)
        return self._samples[key]

    def in_bbox(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of ``points`` (N, 3) inside the axis-aligned bounding box grown by ``margin``."""
        return np.all((points >= self.bbox_min - margin) & (points <= self.bbox_max + margin),
                      axis=1)

    @property
    def n_faces(self) -> int:
        """Count the merged faces."""
        return len(self.face_normals)

    @property
    def n_edges(self) -> int:
        """Count the edges (between two different merged faces)."""
        return len(self.edge_vertices)

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Generalised winding number of the surface at ``points`` [m] (N, 3): ~1 inside."""
        return _winding(points, self.tri_corners)

    def distance_to_surface(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance [m] from ``points`` (N, 3) to the surface, shape (N,)."""
        return min_triangle_distance(points, self.tri_corners)

    def face_distance(self, face: int, points: np.ndarray) -> np.ndarray:
        """Distance [m] from points (N, 3) to the planar region of ``face`` (not its plane)."""
        return min_triangle_distance(points, self._face_tris[face])

    def faces_distance(self, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
        """
        Distance [m] from each point to the planar region of its own face.

        ``faces_distance(faces, points)[i] == face_distance(faces[i], points[i:i + 1])[0]``
        (the same arithmetic), for many faces in one call.

        :param faces: face index per point, shape (N,).
        :param points: query points [m], shape (N, 3).
        :returns: distances [m], shape (N,).
        """
        faces = np.asarray(faces, dtype=np.int64).reshape(-1)
        P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        if not _HAVE_NUMBA:
            out = np.empty(len(P))
            for f in np.unique(faces):
                sel = faces == f
                out[sel] = self.face_distance(int(f), P[sel])
            return out
        if self._face_tri_table is None:
            count = np.array([len(t) for t in self.face_triangles], dtype=np.int64)
            start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
            index = np.concatenate(self.face_triangles).astype(np.int64) if len(count) \
                else np.zeros(0, dtype=np.int64)
            self._face_tri_table = (start, count, index,
                                    np.ascontiguousarray(self.tri_corners, dtype=float))
        start, count, index, tris = self._face_tri_table
        return _face_dist_kernel(P, faces, start, count, index, tris)

    def penetration_of(self, points: np.ndarray, threshold: float) -> float:
        """
        Return the largest distance [m] to the surface of the points inside the solid, or 0.

        A point is inside when it lies in the bounding box and the winding number there
        exceeds ``threshold``; the same tests and values as ``in_bbox``, :meth:`contains`
        and :meth:`distance_to_surface` (one compiled pass).

        :param points: query points [m], shape (N, 3).
        """
        P = np.ascontiguousarray(points, dtype=float).reshape(-1, 3)
        if not _HAVE_NUMBA or len(self.tri_corners) == 0:
            P = P[self.in_bbox(P)]
            if len(P) == 0:
                return 0.0
            inside = self.contains(P) > threshold
            return float(self.distance_to_surface(P[inside]).max()) if np.any(inside) \
                else 0.0
        return float(_depth_kernel(P, self.bbox_min, self.bbox_max,
                                   np.ascontiguousarray(self.tri_corners, dtype=float),
                                   float(threshold)))

    def face_point(self, face: int) -> np.ndarray:
        """Return a point [m] on ``face`` (its first triangle's first corner)."""
        return self.tri_corners[self.face_triangles[face][0], 0]

    def transformed_vertices(self, T: np.ndarray) -> np.ndarray:
        """Vertex positions after the 4x4 transform ``T``, shape (N, 3)."""
        return self.vertices @ T[:3, :3].T + T[:3, 3]


def polyhedron_from_mesh(mesh: PolygonMesh, name: Optional[str] = None,
                         angle_tolerance: float = 1e-6,
                         distance_tolerance: float = 1e-9) -> Polyhedron:
    """
    Build a :class:`Polyhedron` from a polygon mesh, merging coplanar adjacent polygons.

    :param mesh: the model; faces counter-clockwise seen from outside, units metres.
    :param name: model name (default: ``mesh.name``).
    :param angle_tolerance: two adjacent polygons are coplanar when their normals differ by
        less than this angle [rad] ...
    :param distance_tolerance: ... and their plane offsets by less than this [m].
    :raises ValueError: if the mesh is empty, has degenerate faces, or is not a closed,
        consistently oriented 2-manifold (every edge must be used exactly twice, in opposite
        directions) -- the message names the offending edge or face.
    """
    name = name if name is not None else mesh.name
    V = np.asarray(mesh.vertices, dtype=float)
    if len(V) == 0 or len(mesh.faces) == 0:
        raise ValueError(f'model {name!r}: empty mesh')
    if not np.all(np.isfinite(V)):
        raise ValueError(f'model {name!r}: vertices contain NaN or infinite values')
    polys = [np.asarray(f, dtype=np.int64) for f in mesh.faces]
    normals = []
    for i, f in enumerate(polys):
        n = _newell(V[f])
        nn = np.linalg.norm(n)
        if nn < 1e-15:
            raise ValueError(f'model {name!r}: face {i} is degenerate (zero area)')
        normals.append(n / nn)
    normals = np.asarray(normals)
    offsets = np.array([normals[i] @ V[f].mean(0) for i, f in enumerate(polys)])

    # directed edges -> polygon
    directed: Dict[Tuple[int, int], int] = {}
    for i, f in enumerate(polys):
        for k in range(len(f)):
            a, b = int(f[k]), int(f[(k + 1) % len(f)])
            if (a, b) in directed:
                raise ValueError(
                    f'model {name!r}: edge ({a}, {b}) is traversed twice in the same direction '
                    f'(faces {directed[(a, b)]} and {i}): inconsistent orientation or '
                    'non-manifold mesh')
            directed[(a, b)] = i
    for (a, b), i in directed.items():
        if (b, a) not in directed:
            raise ValueError(
                f'model {name!r} is not closed: edge ({a}, {b}) of face {i} has no opposite '
                'face (open boundary or T-junction)')

    # union-find merge of coplanar neighbours
    parent = list(range(len(polys)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    cos_tol = np.cos(angle_tolerance)
    scale = max(1.0, float(np.abs(V).max()))
    for (a, b), i in directed.items():
        j = directed[(b, a)]
        if i < j and normals[i] @ normals[j] >= cos_tol \
                and abs(offsets[i] - offsets[j]) <= distance_tolerance * scale:
            ri, rj = find(i), find(j)
            if ri != rj:
                parent[rj] = ri
    roots: Dict[int, int] = {}
    poly_face = np.empty(len(polys), dtype=np.int64)
    for i in range(len(polys)):
        poly_face[i] = roots.setdefault(find(i), len(roots))
    n_faces = len(roots)
    face_normals = np.zeros((n_faces, 3))
    area_sum = np.zeros(n_faces)
    tris: List[List[int]] = []
    tri_face: List[int] = []
    for i, f in enumerate(polys):
        area = np.linalg.norm(_newell(V[f]))
        face_normals[poly_face[i]] += area * normals[i]
        area_sum[poly_face[i]] += area
        for t in _triangulate_polygon(V, f, normals[i]):
            tris.append(t)
            tri_face.append(int(poly_face[i]))
    face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
    face_offsets = np.zeros(n_faces)
    for i, f in enumerate(polys):
        face_offsets[poly_face[i]] += np.linalg.norm(_newell(V[f])) * (
            face_normals[poly_face[i]] @ V[f].mean(0))
    face_offsets /= area_sum

    edges: List[Tuple[int, int]] = []
    edge_faces: List[Tuple[int, int]] = []
    for (a, b), i in directed.items():
        j = directed[(b, a)]
        fi, fj = int(poly_face[i]), int(poly_face[j])
        if fi == fj or a > b:
            continue  # interior edge of a merged face, or the twin was / will be recorded
        edges.append((a, b))
        edge_faces.append((fi, fj))
    # canonical order: sorted by vertex pair, independent of dictionary order
    order = sorted(range(len(edges)), key=lambda k: edges[k])
    edge_vertices = np.array([edges[k] for k in order], dtype=np.int64).reshape(-1, 2)
    edge_faces_arr = np.array([edge_faces[k] for k in order], dtype=np.int64).reshape(-1, 2)
    d = V[edge_vertices[:, 1]] - V[edge_vertices[:, 0]]
    cr = np.cross(face_normals[edge_faces_arr[:, 0]], face_normals[edge_faces_arr[:, 1]])
    edge_convex = np.einsum('ij,ij->i', cr, d) > 0
    vertex_edges: List[List[int]] = [[] for _ in range(len(V))]
    for e, (a, b) in enumerate(edge_vertices):
        vertex_edges[a].append(e)
        vertex_edges[b].append(e)
    return Polyhedron(
        name=name, vertices=V, triangles=np.asarray(tris, dtype=np.int64),
        triangle_face=np.asarray(tri_face, dtype=np.int64), face_normals=face_normals,
        face_offsets=face_offsets, edge_vertices=edge_vertices, edge_faces=edge_faces_arr,
        edge_convex=edge_convex,
        vertex_edges=[np.asarray(e, dtype=np.int64) for e in vertex_edges])


def load_polyhedron(source: os.PathLike | str | PolygonMesh,
                    directories: Optional[Sequence[Path]] = None) -> Polyhedron:
    """
    Load a polyhedron from a model name, a file (OBJ, PLY or STL, metres) or a mesh.

    A bare name (no suffix, not an existing file) is resolved with
    :func:`stereo_manip_tools.mesh_io.find_model`. OBJ files are read with
    :func:`stereo_manip_tools.mesh_io.load_obj` (polygon faces and vertex order preserved); PLY
    and STL through open3d (duplicated vertices welded, triangles merged into planar faces).

    :raises FileNotFoundError: if the model cannot be found.
    :raises ValueError: if the model is not a closed, consistently oriented polyhedron.
    """
    if isinstance(source, PolygonMesh):
        return polyhedron_from_mesh(source)
    path = Path(source)
    if path.exists() and not path.is_file():
        raise ValueError(f'model {path} is not a regular file (FIFO, device or directory); '
                         'refusing to read it')
    if not path.suffix and not path.is_file():
        path = find_model(str(source), directories)
    suffix = path.suffix.lower()
    if suffix == '.obj':
        return polyhedron_from_mesh(load_obj(path))
    if suffix in ('.ply', '.stl'):
        if not path.is_file():
            raise FileNotFoundError(f'model file {path} does not exist')
        import open3d as o3d  # imported lazily: heavy, only needed for these formats
        m = o3d.io.read_triangle_mesh(str(path))
        m.remove_duplicated_vertices()
        m.remove_degenerate_triangles()
        V = np.asarray(m.vertices, dtype=float)
        F = np.asarray(m.triangles, dtype=np.int64)
        if len(F) == 0:
            raise ValueError(f'{path}: no triangles read')
        return polyhedron_from_mesh(PolygonMesh(V, list(F), path.stem))
    raise ValueError(f'{path}: unsupported model format {suffix!r} (use .obj, .ply or .stl)')


def check_model_units(poly: Polyhedron, low: float = 0.005, high: float = 2.0,
                      refuse: float = 10.0) -> List[str]:
    """
    Plausibility of a model's size for metres (REP 103).

    :returns: warnings (size below ``low`` or above ``high`` metres across).
    :raises ValueError: above ``refuse`` metres across (a model in millimetres is 1000x).
    """
    size = poly.size
    if not np.isfinite(size) or size > refuse:
        raise ValueError(f'model {poly.name!r} is {size:.4g} m across: implausible for metres '
                         '(a model in millimetres? scale it by 0.001)')
    out = []
    if size > high or size < low:
        out.append(f'model {poly.name!r} is {size:.4g} m across: check that its units are '
                   'metres')
    return out
