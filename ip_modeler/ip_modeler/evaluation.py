"""
Evaluation of implicit-polynomial fits: true distances, normals, spurious sheets, meshes.

* :func:`zero_set_mesh` - the zero set ``f = 0`` inside a box as a triangle mesh (marching
  cubes, scikit-image), in the data frame [m].
* :func:`distance_to_zero_set` - the true (geometric) distance of each point to the zero set,
  not the first-order ``|f| / |grad f|``: the smaller of the exact distance to the marching-cubes
  mesh (open3d ``RaycastingScene``) and the length of a Newton projection onto ``f = 0``; both
  are distances to points of the zero set (to within the mesh's interpolation error).
* :func:`normal_agreement` - |cos| between ``grad f`` and reference normals.
* :func:`spurious_sheets` - connected pieces of the zero set inside the data's bounding region
  that come nowhere near the data.
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple

from ip_modeler.fitting import ImplicitPolynomialModel
from ip_modeler.monomials import evaluate_polynomial_on_grid
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

__all__ = [
    'bounding_region',
    'zero_set_mesh',
    'project_to_zero_set',
    'distance_to_zero_set',
    'normal_agreement',
    'spurious_sheets',
    'evaluate_model',
]


def bounding_region(points: np.ndarray, margin: float = 0.1) -> Tuple[np.ndarray, np.ndarray]:
    """
    Axis-aligned box of the points grown by ``margin`` times its largest side on each side.

    :returns: (lower (3,), upper (3,)) corners [m].
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    lo, hi = P.min(axis=0), P.max(axis=0)
    pad = margin * float(np.max(hi - lo))
    return lo - pad, hi + pad


def zero_set_mesh(model: ImplicitPolynomialModel, lower: np.ndarray, upper: np.ndarray,
                  resolution: int = 64) -> Tuple[np.ndarray, np.ndarray]:
    """
    Triangle mesh of ``f = 0`` inside the box [lower, upper] by marching cubes.

    :param model: fitted polynomial.
    :param lower: (3,) box corner [m], data frame.
    :param upper: (3,) opposite corner [m].
    :param resolution: grid samples along the longest side (>= 8).
    :returns: (vertices (V, 3) [m], triangles (F, 3) int); both empty if f does not change
        sign in the box.
    """
    from skimage.measure import marching_cubes

    if resolution < 8:
        raise ValueError(f'resolution must be >= 8, got {resolution}')
    lower = np.asarray(lower, dtype=float).reshape(3)
    upper = np.asarray(upper, dtype=float).reshape(3)
    if np.any(upper <= lower):
        raise ValueError(f'empty box: lower {lower}, upper {upper}')
    h = float(np.max(upper - lower)) / (resolution - 1)
    axes = [np.arange(lower[i], upper[i] + 0.5 * h, h) for i in range(3)]
    axes = [a if len(a) >= 2 else np.array([lower[i], upper[i]]) for i, a in enumerate(axes)]
    norm_axes = [(a - model.centre[i]) / model.scale for i, a in enumerate(axes)]
    F = evaluate_polynomial_on_grid(model.coefficients, *norm_axes)
    if not (F.min() < 0.0 < F.max()):
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    spacing = tuple(float(a[1] - a[0]) for a in axes)
    verts, faces, _, _ = marching_cubes(F, level=0.0, spacing=spacing)
    return verts + lower, faces.astype(np.int64)


def project_to_zero_set(model: ImplicitPolynomialModel, points: np.ndarray,
                        iterations: int = 30, tol: float = 1e-12
                        ) -> Tuple[np.ndarray, np.ndarray]:
    """
    Newton projection ``x <- x - f grad f / |grad f|^2`` onto the zero set.

    :returns: (projected points (N, 3) [m], converged mask (N,)).
    """
    X = np.array(points, dtype=float).reshape(-1, 3)
    active = np.ones(len(X), dtype=bool)
    for _ in range(iterations):
        if not active.any():
            break
        f = model.value(X[active])
        g = model.gradient(X[active])
        gg = np.einsum('ij,ij->i', g, g)
        ok = gg > 0
        step = np.zeros_like(g)
        step[ok] = (f[ok] / gg[ok])[:, None] * g[ok]
        X[active] -= step
        still = np.linalg.norm(step, axis=1) > tol * model.scale
        idx = np.flatnonzero(active)
        active[idx[~still]] = False
    f = model.value(X)
    g = np.linalg.norm(model.gradient(X), axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        converged = np.isfinite(f) & (np.abs(f) <= 1e-9 * np.maximum(g * model.scale, 1e-300))
    return X, converged


def distance_to_zero_set(model: ImplicitPolynomialModel, points: np.ndarray,
                         mesh: Optional[Tuple[np.ndarray, np.ndarray]] = None,
                         resolution: int = 96) -> np.ndarray:
    """
    Compute the true distance [m] from each point to the zero set of ``model``.

    :param points: (N, 3) [m].
    :param mesh: optional zero-set mesh (vertices, triangles) covering the points' region;
        computed over :func:`bounding_region` (margin 0.25) when omitted.
    :returns: (N,) distances; ``inf`` where neither the mesh nor a Newton projection finds
        the zero set.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    if mesh is None:
        mesh = zero_set_mesh(model, *bounding_region(P, 0.25), resolution=resolution)
    d = np.full(len(P), np.inf)
    V, T = mesh
    if len(T):
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)),
                            o3d.core.Tensor(T.astype(np.uint32)))
        d = scene.compute_distance(o3d.core.Tensor(P.astype(np.float32))).numpy()
        d = d.astype(float)
    proj, ok = project_to_zero_set(model, P)
    dn = np.linalg.norm(proj - P, axis=1)
    return np.where(ok, np.minimum(d, dn), d)


def normal_agreement(model: ImplicitPolynomialModel, points: np.ndarray,
                     normals: np.ndarray) -> Dict[str, float]:
    """
    Agreement of ``grad f`` at the points with reference normals (sign ignored).

    :returns: ``mean_abs_cos`` and ``mean_angle_deg`` (angle between the lines).
    """
    g = model.gradient(points)
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    gn = np.linalg.norm(g, axis=1) * np.linalg.norm(n, axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        c = np.abs(np.einsum('ij,ij->i', g, n)) / gn
    c = np.clip(np.nan_to_num(c, nan=0.0), 0.0, 1.0)
    return {'mean_abs_cos': float(c.mean()),
            'mean_angle_deg': float(np.degrees(np.arccos(c)).mean())}


def spurious_sheets(mesh: Tuple[np.ndarray, np.ndarray], points: np.ndarray,
                    tol: float, region: Optional[Tuple[np.ndarray, np.ndarray]] = None
                    ) -> Dict[str, float]:
    """
    Find connected pieces of the zero-set mesh that reach ``region`` but never come near data.

    The mesh should cover more than ``region`` so that a surface leaving the region and
    coming back is not cut into separate pieces by the clipping.

    :param mesh: zero-set mesh (vertices [m], triangles).
    :param points: (N, 3) data [m].
    :param tol: distance [m] within which a piece counts as explaining data.
    :param region: (lower, upper) box [m] a piece must enter to count (default: all pieces).
    :returns: ``count`` (spurious pieces), ``components`` (pieces entering the region) and
        ``area_fraction`` (share of the mesh area inside the region farther than ``tol``
        from every data point, spurious pieces or not).
    """
    V, T = mesh
    if len(T) == 0:
        return {'count': 0, 'components': 0, 'area_fraction': 0.0}
    rows = np.concatenate([T[:, 0], T[:, 1], T[:, 2]])
    cols = np.concatenate([T[:, 1], T[:, 2], T[:, 0]])
    adj = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(V), len(V)))
    n_comp, labels = connected_components(adj, directed=False)
    used = np.unique(T)
    tree = cKDTree(np.asarray(points, dtype=float).reshape(-1, 3))
    dv, _ = tree.query(V)
    comp_min = np.full(n_comp, np.inf)
    np.minimum.at(comp_min, labels[used], dv[used])
    if region is None:
        inside_v = np.ones(len(V), dtype=bool)
    else:
        lo, hi = (np.asarray(x, dtype=float).reshape(1, 3) for x in region)
        inside_v = np.all((V >= lo) & (V <= hi), axis=1)
    enters = np.zeros(n_comp, dtype=bool)
    enters[labels[used][inside_v[used]]] = True
    present = enters & np.isfinite(comp_min)
    count = int(np.sum(comp_min[present] > tol))
    tri = V[T]
    centroid = tri.mean(axis=1)
    if region is not None:
        inside_t = np.all((centroid >= lo) & (centroid <= hi), axis=1)
        tri, centroid = tri[inside_t], centroid[inside_t]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    dc, _ = tree.query(centroid) if len(centroid) else (np.zeros(0), None)
    total = float(area.sum())
    far = float(area[dc > tol].sum())
    return {'count': count, 'components': int(present.sum()),
            'area_fraction': far / total if total > 0 else 0.0}


def evaluate_model(model: ImplicitPolynomialModel, points: np.ndarray,
                   normals: Optional[np.ndarray] = None, size: Optional[float] = None,
                   resolution: int = 96, sheet_tol: float = 0.1) -> Dict[str, float]:
    """
    All evaluation figures of one fit against (clean) reference points.

    :param points: (N, 3) reference points [m] (noise-free surface samples if available).
    :param normals: (N, 3) reference normals, optional.
    :param size: object size [m] for relative figures (default: bounding-box diagonal).
    :param resolution: marching-cubes samples along the longest side of the evaluation box
        (the data's bounding box grown by 35 % of its largest side on every side).
    :param sheet_tol: spurious-sheet distance as a fraction of ``size``; pieces are counted
        if they enter the bounding box grown by 10 %.
    :returns: dict with ``rms_distance``, ``max_distance`` [m], their ratios to ``size``,
        normal agreement, spurious-sheet figures and the mesh size.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    region = bounding_region(P, 0.1)
    if size is None:
        size = float(np.linalg.norm(P.max(axis=0) - P.min(axis=0)))
    mesh = zero_set_mesh(model, *bounding_region(P, 0.35), resolution=resolution)
    d = distance_to_zero_set(model, P, mesh=mesh)
    out = {
        'rms_distance': float(np.sqrt(np.mean(d ** 2))),
        'max_distance': float(np.max(d)),
    }
    out['rms_distance_rel'] = out['rms_distance'] / size
    out['max_distance_rel'] = out['max_distance'] / size
    if normals is not None:
        out.update(normal_agreement(model, P, normals))
    sheets = spurious_sheets(mesh, P, sheet_tol * size, region)
    out['spurious_sheets'] = sheets['count']
    out['zero_set_components'] = sheets['components']
    out['far_area_fraction'] = sheets['area_fraction']
    out['mesh_triangles'] = int(len(mesh[1]))
    return out
