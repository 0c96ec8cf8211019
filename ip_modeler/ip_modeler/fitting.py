"""
Implicit-polynomial fitting with adaptive degree (Section 5, Eqs. 19-22) and baselines.

Pipeline of :func:`fit_implicit_polynomial`:

1. check the cloud (finite, enough points, not planar/collinear) and normalise it: centre at
   the centroid, divide by the largest distance to it, so all points lie in the unit ball (the
   transform is returned with the model: ``x_n = (x - centre) / scale``);
2. build the 3L data set (Blane et al. 2000; the chapter's footnote 5): the points with target
   value 0 plus two layers offset by +-c along the unit normals with targets +-c, so ``M a = b``
   (Eq. 20) has ``b != 0`` and a plain linear least-squares solve applies;
3. raise the degree 1, 2, ...: append the new degree's monomial columns to an
   :class:`~ip_modeler.incremental_qr.IncrementalQR` and solve ``R a = Q^T b`` (Eq. 22);
   unstable columns (small ``|r_jj|``) are dropped or ridge-regularised, and a small global
   ridge (RR) keeps the polynomial tame away from the data (fewer spurious sheets);
4. stop at the first degree whose RMS first-order distance ``|f| / |grad f|`` at the points
   (in metres) is at most ``target_rms`` or at ``max_degree``; if the target is never met the
   degree with the lowest RMS is returned (a degree that does not improve the fit by
   ``min_improvement`` for ``patience`` consecutive degrees ends the search early).

Baselines for comparison (same normalisation): the 3L system solved from scratch per degree
(:func:`fit_3l_from_scratch`, ``numpy.linalg.lstsq`` or Householder QR), Taubin's method
(:func:`fit_taubin`) and gradient-one (:func:`fit_gradient_one`, Tasdizen et al. 2000).
All coordinates in metres unless stated "normalised"; points and normals are (N, 3) arrays.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import time
from typing import Dict, List, Optional, Tuple

from ip_modeler.incremental_qr import IncrementalQR, STABILIZATION_MODES
from ip_modeler.monomials import (
    degree_slice, evaluate_polynomial, evaluate_polynomial_gradient, monomial_count,
    monomial_gradient_matrices, monomial_matrix, MONOMIAL_ORDER)
import numpy as np
from scipy.linalg import eigh, solve_triangular
from scipy.spatial import cKDTree

__all__ = [
    'ImplicitPolynomialModel',
    'DegreeStep',
    'FitResult',
    'MAX_SUPPORTED_DEGREE',
    'DEFAULT_3L_OFFSET',
    'check_point_cloud',
    'normalize_points',
    'estimate_normals',
    'three_layer_data',
    'fit_implicit_polynomial',
    'fit_3l_from_scratch',
    'fit_taubin',
    'fit_gradient_one',
]

MAX_SUPPORTED_DEGREE = 16
# 3L layer offset c (fraction of the normalisation scale); see the package README for the
# offsets tried (0.005-0.02) and why 0.02 was kept.
DEFAULT_3L_OFFSET = 0.02


@dataclass
class ImplicitPolynomialModel:
    """
    An implicit polynomial surface ``f(x) = 0`` fitted to data (Eq. 19).

    :ivar degree: total degree n.
    :ivar coefficients: (K,) coefficients in graded_lex order, in normalised coordinates
        ``x_n = (x - centre) / scale``.
    :ivar centre: (3,) normalisation centre [m] in the data frame.
    :ivar scale: normalisation scale [m].
    :ivar method: fitting method, e.g. ``'3L incremental QR'``.
    :ivar status: notes (dropped / regularised columns, stopping reason).
    """

    degree: int
    coefficients: np.ndarray
    centre: np.ndarray
    scale: float
    method: str = ''
    status: str = ''
    monomial_order: str = MONOMIAL_ORDER

    def __post_init__(self) -> None:
        self.coefficients = np.asarray(self.coefficients, dtype=float).reshape(-1)
        self.centre = np.asarray(self.centre, dtype=float).reshape(3)
        self.scale = float(self.scale)
        if self.coefficients.size != monomial_count(self.degree):
            raise ValueError(f'degree {self.degree} needs {monomial_count(self.degree)} '
                             f'coefficients, got {self.coefficients.size}')
        if not self.scale > 0:
            raise ValueError(f'scale must be > 0, got {self.scale}')

    def normalize(self, points: np.ndarray) -> np.ndarray:
        """Data-frame points [m] (N, 3) to normalised coordinates."""
        return (np.asarray(points, dtype=float).reshape(-1, 3) - self.centre) / self.scale

    def denormalize(self, points_n: np.ndarray) -> np.ndarray:
        """Normalised coordinates (N, 3) back to the data frame [m]."""
        return np.asarray(points_n, dtype=float).reshape(-1, 3) * self.scale + self.centre

    def value(self, points: np.ndarray) -> np.ndarray:
        """Evaluate f at data-frame points [m], shape (N,) (f: of normalised coordinates)."""
        return evaluate_polynomial(self.coefficients, self.normalize(points))

    def gradient(self, points: np.ndarray) -> np.ndarray:
        """Gradient of f with respect to data-frame coordinates [1/m], shape (N, 3)."""
        return evaluate_polynomial_gradient(self.coefficients, self.normalize(points)) / self.scale

    def first_order_distance(self, points: np.ndarray) -> np.ndarray:
        """Approximate distance [m] ``|f| / |grad f|`` of each point to the zero set, (N,)."""
        f = self.value(points)
        g = np.linalg.norm(self.gradient(points), axis=1)
        with np.errstate(divide='ignore', invalid='ignore'):
            d = np.abs(f) / g
        return np.where(g > 0, d, np.inf)


@dataclass
class DegreeStep:
    """Diagnostics of one degree of the adaptive fit."""

    degree: int
    rms_first_order: float  # [m], at the data points
    columns: int
    dropped: int
    regularised: int
    min_diagonal_ratio: float  # smallest |r_jj| / ||m_j|| among this degree's columns
    condition_estimate: float  # max |r_ii| / min |r_ii| over all accepted columns
    seconds: float  # cumulative time since the fit started
    ridge: float = 0.0  # global ridge weight used (raised by the spurious-sheet check)
    spurious_sheets: int = -1  # pieces found by the check at the final ridge (-1: not checked)


@dataclass
class FitResult:
    """Result of :func:`fit_implicit_polynomial`: the chosen model plus every degree tried."""

    model: ImplicitPolynomialModel
    steps: List[DegreeStep] = field(default_factory=list)
    models: Dict[int, ImplicitPolynomialModel] = field(default_factory=dict)
    stop_reason: str = ''
    seconds: float = 0.0


def check_point_cloud(points: np.ndarray, min_points: int = 1, name: str = 'points',
                      degenerate_tol: float = 1e-6) -> np.ndarray:
    """
    Validate a point cloud and return it as float (N, 3).

    :param points: (N, 3) coordinates.
    :param min_points: the least number of points needed (e.g. the coefficient count).
    :param degenerate_tol: a cloud whose second (third) principal extent is below this
        fraction of the first is collinear (planar).
    :raises ValueError: with a message naming the problem (shape, NaN/inf, too few points,
        planar or collinear cloud).
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3:
        raise ValueError(f'{name} must have shape (N, 3), got {P.shape}')
    bad = ~np.all(np.isfinite(P), axis=1)
    if bad.any():
        raise ValueError(f'{name} contain {int(bad.sum())} non-finite (NaN/inf) rows of '
                         f'{len(P)}; remove them before fitting')
    if len(P) < min_points:
        raise ValueError(f'{len(P)} points are fewer than the {min_points} needed '
                         '(the number of polynomial coefficients)')
    if len(P) < 4:
        raise ValueError(f'{len(P)} points cannot define a surface (need at least 4)')
    s = np.linalg.svd(P - P.mean(axis=0), compute_uv=False)
    if s[0] <= 0:
        raise ValueError(f'{name} are all the same point')
    if s[1] < degenerate_tol * s[0]:
        raise ValueError(f'{name} are collinear (principal extents {s[0]:.3g}, {s[1]:.3g}, '
                         f'{s[2]:.3g}): no unique implicit surface through them')
    if s[2] < degenerate_tol * s[0]:
        raise ValueError(f'{name} are planar (principal extents {s[0]:.3g}, {s[1]:.3g}, '
                         f'{s[2]:.3g}): every f = plane * g vanishes on them, so no unique '
                         'implicit polynomial; fit a plane instead')
    return P


def normalize_points(points: np.ndarray) -> Tuple[np.ndarray, np.ndarray, float]:
    """
    Centre at the centroid and scale into the unit ball.

    :returns: (normalised points (N, 3), centre (3,) [m], scale [m]) with
        ``normalised = (points - centre) / scale`` and ``max |normalised| = 1``.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    centre = P.mean(axis=0)
    scale = float(np.max(np.linalg.norm(P - centre, axis=1)))
    if not scale > 0:
        raise ValueError('cannot normalise: all points coincide')
    return (P - centre) / scale, centre, scale


def estimate_normals(points: np.ndarray, k: int = 16,
                     viewpoint: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Estimate unit normals by PCA of the k nearest neighbours, oriented toward ``viewpoint``.

    :param points: (N, 3) [m].
    :param k: neighbours per point (>= 3).
    :param viewpoint: (3,) sensor position [m] in the same frame; surfaces seen by a sensor
        face it, so this orients normals outward. ``None`` orients them away from the centroid
        (right for star-shaped closed objects).
    :returns: (N, 3) unit normals.
    """
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    k = int(min(max(k, 3), len(P)))
    _, idx = cKDTree(P).query(P, k=k)
    nb = P[idx] - P[idx].mean(axis=1, keepdims=True)
    cov = np.einsum('nki,nkj->nij', nb, nb)
    _, vecs = np.linalg.eigh(cov)
    normals = vecs[:, :, 0]
    if viewpoint is None:
        ref = P - P.mean(axis=0)
    else:
        ref = np.asarray(viewpoint, dtype=float).reshape(1, 3) - P
    flip = np.einsum('ij,ij->i', normals, ref) < 0
    normals[flip] *= -1.0
    return normals


def three_layer_data(points_n: np.ndarray, normals: np.ndarray,
                     offset: float) -> Tuple[np.ndarray, np.ndarray]:
    """
    3L data set (Blane et al. 2000): points (target 0) and layers +-c along the normals.

    :param points_n: (N, 3) normalised points.
    :param normals: (N, 3) outward normals (normalised to unit length here).
    :param offset: layer offset c > 0 in normalised units.
    :returns: (X (3N, 3), b (3N,)) with b = 0, +c, -c for the three layers.
    """
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    if n.shape != points_n.shape:
        raise ValueError(f'normals shape {n.shape} differs from points shape '
                         f'{points_n.shape}')
    if not np.all(np.isfinite(n)):
        raise ValueError('normals contain NaN/inf')
    length = np.linalg.norm(n, axis=1)
    if np.any(length < 1e-12):
        raise ValueError(f'{int(np.sum(length < 1e-12))} normals have zero length')
    n = n / length[:, None]
    if not offset > 0:
        raise ValueError(f'offset must be > 0, got {offset}')
    X = np.vstack([points_n, points_n + offset * n, points_n - offset * n])
    N = len(points_n)
    b = np.concatenate([np.zeros(N), np.full(N, offset), np.full(N, -offset)])
    return X, b


_RIDGE_STEP = 10.0 ** 0.5


def _spurious_sheet_count(model: 'ImplicitPolynomialModel', points: np.ndarray,
                          resolution: int) -> int:
    """
    Spurious zero-set pieces of ``model`` judged on the input ``points`` [m] alone.

    Same rule as :func:`ip_modeler.evaluation.spurious_sheets` (box grown 10 %, tolerance 10 %
    of the box's largest side), on a coarser grid.
    """
    from ip_modeler.evaluation import bounding_region, spurious_sheets, zero_set_mesh

    size = float(np.max(points.max(axis=0) - points.min(axis=0)))
    mesh = zero_set_mesh(model, *bounding_region(points, 0.35), resolution=resolution)
    return int(spurious_sheets(mesh, points, 0.1 * size, bounding_region(points, 0.1))['count'])


def _rms_first_order(a: np.ndarray, M: np.ndarray, G: np.ndarray, scale: float) -> float:
    """RMS of |f|/|grad f| [m] at the data points from their monomial (gradient) matrices."""
    k = a.size
    f = M[:, :k] @ a
    g = np.sqrt(sum((G[i][:, :k] @ a) ** 2 for i in range(3)))
    with np.errstate(divide='ignore', invalid='ignore'):
        d = np.where(g > 0, np.abs(f) / g, np.inf)
    return float(np.sqrt(np.mean(d ** 2)) * scale)


def _prepare(points: np.ndarray, normals: Optional[np.ndarray], degree: int,
             viewpoint: Optional[np.ndarray], need_normals: bool = True):
    if not 1 <= degree <= MAX_SUPPORTED_DEGREE:
        raise ValueError(f'degree must be in [1, {MAX_SUPPORTED_DEGREE}], got {degree}')
    P = check_point_cloud(points, min_points=monomial_count(degree))
    if need_normals:
        if normals is None:
            normals = estimate_normals(P, viewpoint=viewpoint)
        normals = np.asarray(normals, dtype=float)
        if normals.shape != P.shape:
            raise ValueError(f'normals must have the shape of points {P.shape}, got '
                             f'{normals.shape}')
        if not np.all(np.isfinite(normals)):
            raise ValueError('normals contain NaN/inf')
    Pn, centre, scale = normalize_points(P)
    return P, normals, Pn, centre, scale


def fit_implicit_polynomial(points: np.ndarray, normals: Optional[np.ndarray] = None, *,
                            max_degree: int = 8, target_rms: float = 0.0, min_degree: int = 1,
                            offset: float = DEFAULT_3L_OFFSET, stabilization: str = 'drop',
                            stability_tol: float = 1e-6, ridge: float = 1e-6,
                            min_improvement: float = 0.05,
                            patience: int = 3, viewpoint: Optional[np.ndarray] = None,
                            variant: str = 'arnoldi', sheet_check: bool = True,
                            max_sheet_ridge: float = 1e-4,
                            sheet_check_resolution: int = 64) -> FitResult:
    """
    Adaptive-degree 3L implicit-polynomial fit by incremental QR (Section 5, Eqs. 19-22).

    :param points: (N, 3) object points [m].
    :param normals: (N, 3) outward normals; estimated by PCA (oriented toward ``viewpoint``)
        when ``None``.
    :param max_degree: highest degree tried (1..16).
    :param target_rms: stop at the first degree whose RMS first-order distance [m] at the
        points is <= this (0: never stop early for accuracy; the best degree is kept).
    :param min_degree: lowest degree that may be returned; the degrees below it are only
        factorised (no sheet check: they cannot be chosen), so a fit warm-started from a
        previous fit's degree (``min_degree`` just below it) skips most of the sheet checks.
    :param offset: 3L layer offset c as a fraction of the normalisation scale (0 < c < 0.5).
    :param stabilization: ``'drop'`` or ``'ridge'`` for columns with small R diagonal, or
        ``'none'``.
    :param stability_tol: threshold on ``|r_jj| / ||m_j||`` below which a column is unstable.
    :param ridge: global ridge-regression weight on all non-constant coefficients (RR,
        Tasdizen et al. 2000), relative to the squared largest column norm; 1e-6 removes most
        spurious zero-set sheets of high degrees at a small cost in accuracy (0: plain LS).
    :param min_improvement: a degree must lower the RMS by this fraction to count as progress.
    :param patience: stop after this many consecutive degrees without progress.
    :param viewpoint: sensor position [m] for orienting estimated normals.
    :param variant: ``'arnoldi'`` (columns ``x * q_parent``, one pass), ``'classical'``
        (BCGS2 on the monomials) or ``'modified'`` (BMGS2); see
        :mod:`ip_modeler.incremental_qr`. All give the same factorisation ``M = QR``.
    :param sheet_check: after each degree's solve, look for spurious zero-set sheets (pieces
        of the zero set inside the input's bounding box grown 10 % that never come within
        10 % of its largest side of an input point) and, while there are any, raise the
        global ridge by sqrt(10) and solve again (up to ``max_sheet_ridge``). The re-solve
        reuses the factorisation; the check costs a marching-cubes pass per solve.
    :param max_sheet_ridge: largest ridge the sheet check may use.
    :param sheet_check_resolution: marching-cubes samples along the longest side of the
        check's grid (the input's bounding box grown 35 %).
    :returns: :class:`FitResult`; ``result.model`` is the selected polynomial.
    :raises ValueError: on bad input (NaN, too few points, planar/collinear cloud, bad
        parameters), with a message naming the problem.
    """
    if not 1 <= min_degree <= max_degree:
        raise ValueError(f'need 1 <= min_degree <= max_degree, got {min_degree}, {max_degree}')
    if not 0.0 < offset < 0.5:
        raise ValueError(f'offset must be in (0, 0.5) (fraction of the scale), got {offset}')
    if ridge < 0 or not np.isfinite(ridge):
        raise ValueError(f'ridge must be finite and >= 0, got {ridge}')
    if target_rms < 0 or not np.isfinite(target_rms):
        raise ValueError(f'target_rms must be finite and >= 0, got {target_rms}')
    if stabilization not in STABILIZATION_MODES:
        raise ValueError(f'stabilization must be one of {STABILIZATION_MODES}')
    t0 = time.perf_counter()
    P, normals, Pn, centre, scale = _prepare(points, normals, min_degree, viewpoint)
    X, b = three_layer_data(Pn, normals, offset)
    N = len(Pn)
    data_cap = ''
    while monomial_count(max_degree) > N:  # no more coefficients than points
        max_degree -= 1
        data_cap = f' (capped by {N} points)'
    min_degree = min(min_degree, max_degree)
    qr = IncrementalQR(b, stabilization=stabilization, stability_tol=stability_tol,
                       variant=variant, capacity=monomial_count(max_degree),
                       points=X if variant == 'arnoldi' else None)
    M_all = monomial_matrix(X, max_degree)  # rows 0..N-1 are the data points themselves
    G_data = monomial_gradient_matrices(None, max_degree, M=M_all[:N])
    result = FitResult(model=None)  # type: ignore[arg-type]
    best: Optional[Tuple[float, int]] = None
    stale = 0
    stop = f'max_degree {max_degree}{data_cap} reached'
    method = f'3L incremental QR ({stabilization}, ridge {ridge:g})'
    for degree in range(1, max_degree + 1):
        cols = slice(0, 4) if degree == 1 else degree_slice(degree)
        before_dropped, before_unstable = len(qr.dropped), len(qr.unstable)
        qr.append(M_all[:, cols])
        a = qr.solve(ridge=ridge)
        used_ridge, sheets = ridge, -1
        if sheet_check and degree >= min_degree and np.all(np.isfinite(a)) \
                and np.any(a[1:]):
            sheets = _spurious_sheet_count(ImplicitPolynomialModel(degree, a, centre, scale),
                                           P, sheet_check_resolution)
            while sheets > 0 and used_ridge * _RIDGE_STEP <= max_sheet_ridge * (1 + 1e-9):
                used_ridge = max(used_ridge, 1e-7) * _RIDGE_STEP
                a = qr.solve(ridge=used_ridge)
                sheets = _spurious_sheet_count(
                    ImplicitPolynomialModel(degree, a, centre, scale), P,
                    sheet_check_resolution)
        if not np.all(np.isfinite(a)) or not np.any(a[1:]):
            rms = float('inf')
        else:
            rms = _rms_first_order(a, M_all[:N], G_data, scale)
        ratios = np.asarray(qr.diagonal_ratio[cols])
        result.steps.append(DegreeStep(
            degree=degree, rms_first_order=rms, columns=monomial_count(degree),
            dropped=len(qr.dropped) - before_dropped,
            regularised=len(qr.unstable) - before_unstable,
            min_diagonal_ratio=float(ratios.min()) if ratios.size else float('nan'),
            condition_estimate=qr.condition_estimate(),
            seconds=time.perf_counter() - t0, ridge=used_ridge, spurious_sheets=sheets))
        notes = (f'degree {degree}: {len(qr.dropped)} columns dropped, {len(qr.unstable)} '
                 f'ridge-regularised, R diagonal condition {qr.condition_estimate():.3g}, '
                 f'ridge {used_ridge:.3g}')
        result.models[degree] = ImplicitPolynomialModel(degree, a, centre, scale, method, notes)
        if degree < min_degree:
            continue
        if target_rms > 0 and rms <= target_rms:
            best = (rms, degree)
            stop = f'target RMS {target_rms:.3g} m met at degree {degree}'
            break
        if best is None or rms < (1.0 - min_improvement) * best[0]:
            stale = 0
        else:
            stale += 1
        if best is None or rms < best[0]:
            best = (rms, degree)
        if stale >= patience:
            stop = (f'no {min_improvement:.0%} RMS improvement over {patience} degrees '
                    f'after degree {best[1]}')
            break
    assert best is not None
    chosen = result.models[best[1]]
    chosen.status = f'{stop}; {chosen.status}'
    result.model = chosen
    result.stop_reason = stop
    result.seconds = time.perf_counter() - t0
    return result


def fit_3l_from_scratch(points: np.ndarray, normals: Optional[np.ndarray], degree: int, *,
                        offset: float = DEFAULT_3L_OFFSET, solver: str = 'lstsq',
                        viewpoint: Optional[np.ndarray] = None) -> ImplicitPolynomialModel:
    """
    Baseline: the 3L system of one degree solved from scratch (no reuse across degrees).

    :param solver: ``'lstsq'`` (``numpy.linalg.lstsq``, SVD based) or ``'householder'``
        (``numpy.linalg.qr`` then back substitution).
    """
    if solver not in ('lstsq', 'householder'):
        raise ValueError(f"solver must be 'lstsq' or 'householder', got {solver!r}")
    P, normals, Pn, centre, scale = _prepare(points, normals, degree, viewpoint)
    X, b = three_layer_data(Pn, normals, offset)
    M = monomial_matrix(X, degree)
    if solver == 'lstsq':
        a = np.linalg.lstsq(M, b, rcond=None)[0]
    else:
        Q, R = np.linalg.qr(M)
        a = solve_triangular(R, Q.T @ b)
    return ImplicitPolynomialModel(degree, a, centre, scale, f'3L {solver}', '')


def fit_taubin(points: np.ndarray, degree: int) -> ImplicitPolynomialModel:
    """
    Baseline: Taubin's method, min sum f^2 / sum |grad f|^2 (generalised eigenproblem).

    The constant coefficient has no gradient, so it is eliminated in closed form and the
    remaining generalised symmetric eigenproblem ``S a' = lambda G a'`` is solved for its
    smallest eigenvalue (Taubin 1991). Needs no normals.
    """
    P, _, Pn, centre, scale = _prepare(points, None, degree, None, need_normals=False)
    M = monomial_matrix(Pn, degree)
    Gm = monomial_gradient_matrices(None, degree, M=M)
    m0, M1 = M[:, 0], M[:, 1:]
    mm = float(m0 @ m0)
    A = M1.T @ M1 - np.outer(M1.T @ m0, m0 @ M1) / mm
    B = sum(Gm[i][:, 1:].T @ Gm[i][:, 1:] for i in range(3))
    A = 0.5 * (A + A.T)
    B = 0.5 * (B + B.T) + 1e-12 * np.trace(B) / B.shape[0] * np.eye(B.shape[0])
    _, vecs = eigh(A, B, subset_by_index=[0, 0])
    a1 = vecs[:, 0]
    a0 = -float(m0 @ (M1 @ a1)) / mm
    a = np.concatenate([[a0], a1])
    a /= np.linalg.norm(a)
    return ImplicitPolynomialModel(degree, a, centre, scale, 'Taubin', '')


def fit_gradient_one(points: np.ndarray, normals: Optional[np.ndarray], degree: int, *,
                     weight: float = 0.01,
                     viewpoint: Optional[np.ndarray] = None) -> ImplicitPolynomialModel:
    """
    Baseline: gradient-one fit (Tasdizen et al. 2000).

    Minimises ``sum f(x_i)^2 + weight * sum |grad f(x_i) - n_i|^2`` (normalised coordinates),
    a linear least-squares problem, so that f behaves like a signed distance near the data.
    The default weight (0.01) was the best of 1, 0.1, 0.01 on a noise-free ellipsoid: a
    polynomial cannot have a unit gradient everywhere on most surfaces, and a large weight
    trades zero-set accuracy for it.
    """
    P, normals, Pn, centre, scale = _prepare(points, normals, degree, viewpoint)
    n = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    M = monomial_matrix(Pn, degree)
    Gm = monomial_gradient_matrices(None, degree, M=M)
    w = np.sqrt(weight)
    A = np.vstack([M, w * Gm[0], w * Gm[1], w * Gm[2]])
    rhs = np.concatenate([np.zeros(len(Pn)), w * n[:, 0], w * n[:, 1], w * n[:, 2]])
    a = np.linalg.lstsq(A, rhs, rcond=None)[0]
    return ImplicitPolynomialModel(degree, a, centre, scale, 'gradient-one', '')
