"""
Monomial bases of implicit polynomials in the graded order of Eq. 19 (pure numpy).

An implicit polynomial (IP) of degree ``n`` in three variables is
``f(x) = sum_{i+j+k <= n} a_ijk x^i y^j z^k = m(x)^T a`` (Eq. 19). The monomials are ordered
``"graded_lex"`` exactly as stated in ``stereo_manip_msgs/ImplicitPolynomial``: by total degree
0, 1, ..., n and, within one degree, exponents ``(i, j, k)`` in descending lexicographic order
(degree 1: x, y, z; degree 2: x^2, xy, xz, y^2, yz, z^2). Raising the degree therefore only
appends columns to the design matrix, which is what the incremental QR of Section 5 reuses.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Optional, Tuple

import numpy as np

__all__ = [
    'MONOMIAL_ORDER',
    'monomial_count',
    'monomial_exponents',
    'degree_slice',
    'monomial_matrix',
    'monomial_gradient_matrices',
    'monomial_shift_indices',
    'evaluate_polynomial',
    'evaluate_polynomial_gradient',
    'evaluate_polynomial_on_grid',
    'coefficient_tensor',
]

MONOMIAL_ORDER = 'graded_lex'


def monomial_count(degree: int) -> int:
    """Count the monomials of total degree <= ``degree``: (n+1)(n+2)(n+3)/6."""
    if degree < 0:
        raise ValueError(f'degree must be >= 0, got {degree}')
    return (degree + 1) * (degree + 2) * (degree + 3) // 6


@lru_cache(maxsize=32)
def _exponents(degree: int) -> np.ndarray:
    rows = []
    for d in range(degree + 1):
        for i in range(d, -1, -1):
            for j in range(d - i, -1, -1):
                rows.append((i, j, d - i - j))
    out = np.array(rows, dtype=np.int64).reshape(-1, 3)
    out.setflags(write=False)
    return out


def monomial_exponents(degree: int) -> np.ndarray:
    """
    Exponents ``(i, j, k)`` of the monomials up to ``degree`` in graded_lex order.

    :param degree: maximum total degree n >= 0.
    :returns: read-only int array of shape (monomial_count(n), 3).
    """
    if degree < 0:
        raise ValueError(f'degree must be >= 0, got {degree}')
    return _exponents(int(degree))


def degree_slice(degree: int) -> slice:
    """Columns of the monomials of total degree exactly ``degree`` (a contiguous block)."""
    start = monomial_count(degree - 1) if degree > 0 else 0
    return slice(start, monomial_count(degree))


def _powers(points: np.ndarray, degree: int) -> np.ndarray:
    """Powers ``P[p, axis, e] = points[p, axis] ** e`` for e = 0..degree, shape (N, 3, n+1)."""
    n_pts = points.shape[0]
    P = np.empty((n_pts, 3, degree + 1))
    P[:, :, 0] = 1.0
    for e in range(1, degree + 1):
        P[:, :, e] = P[:, :, e - 1] * points
    return P


def monomial_matrix(points: np.ndarray, degree: int, min_degree: int = 0) -> np.ndarray:
    """
    Design matrix M whose row p is m(x_p)^T (Eq. 20), columns of degrees min_degree..degree.

    :param points: (N, 3) coordinates (normally the normalised coordinates of the fit).
    :param degree: highest total degree n.
    :param min_degree: lowest total degree of the returned columns (0 gives the full basis).
    :returns: Fortran-ordered float array of shape (N, monomial_count(n) -
        monomial_count(min_degree - 1)).
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    E = monomial_exponents(degree)[monomial_count(min_degree - 1) if min_degree > 0 else 0:]
    P = _powers(pts, degree)
    M = np.empty((pts.shape[0], E.shape[0]), order='F')
    for c, (i, j, k) in enumerate(E):
        np.multiply(P[:, 0, i], P[:, 1, j], out=M[:, c])
        M[:, c] *= P[:, 2, k]
    return M


@lru_cache(maxsize=32)
def _derivative_index(degree: int) -> Tuple[np.ndarray, np.ndarray]:
    """For each axis and monomial, (index of the lowered monomial, exponent factor)."""
    E = _exponents(degree)
    lookup = {tuple(e): c for c, e in enumerate(E)}
    idx = np.zeros((3, len(E)), dtype=np.int64)
    fac = np.zeros((3, len(E)))
    for c, e in enumerate(E):
        for axis in range(3):
            if e[axis] > 0:
                lowered = list(e)
                lowered[axis] -= 1
                idx[axis, c] = lookup[tuple(lowered)]
                fac[axis, c] = e[axis]
    return idx, fac


def monomial_shift_indices(degree: int) -> Tuple[np.ndarray, np.ndarray]:
    """
    Neighbours of each monomial in the graded_lex basis up to ``degree``.

    :param degree: maximum total degree n >= 0.
    :returns: ``(lowered, raised)``, int arrays of shape (3, monomial_count(n)):
        ``lowered[axis, c]`` is the index of monomial c divided by x_axis and
        ``raised[axis, c]`` the index of monomial c times x_axis; -1 where that monomial does
        not exist (exponent 0, or degree above n).
    """
    if degree < 0:
        raise ValueError(f'degree must be >= 0, got {degree}')
    return _shift_indices(int(degree))


@lru_cache(maxsize=32)
def _shift_indices(degree: int) -> Tuple[np.ndarray, np.ndarray]:
    idx, fac = _derivative_index(degree)
    lowered = np.where(fac > 0, idx, -1)
    raised = np.full_like(lowered, -1)
    for axis in range(3):
        has = fac[axis] > 0
        raised[axis, idx[axis, has]] = np.flatnonzero(has)
    lowered.setflags(write=False)
    raised.setflags(write=False)
    return lowered, raised


def monomial_gradient_matrices(points: Optional[np.ndarray], degree: int,
                               M: Optional[np.ndarray] = None) -> np.ndarray:
    """
    Partial derivatives of the monomials: G[axis] row p is d m(x_p)^T / d x_axis.

    :param points: (N, 3) coordinates (unused when ``M`` is given).
    :param degree: highest total degree n.
    :param M: optional precomputed ``monomial_matrix(points, degree)`` (saves work).
    :returns: array of shape (3, N, monomial_count(n)).
    """
    if M is None:
        M = monomial_matrix(points, degree)
    idx, fac = _derivative_index(int(degree))
    return np.stack([M[:, idx[a]] * fac[a] for a in range(3)])


def _check_coefficients(coefficients: np.ndarray) -> Tuple[np.ndarray, int]:
    a = np.asarray(coefficients, dtype=float).reshape(-1)
    n = 0
    while monomial_count(n) < a.size:
        n += 1
    if monomial_count(n) != a.size:
        raise ValueError(f'{a.size} coefficients is not a full graded basis '
                         '(expected (n+1)(n+2)(n+3)/6 for some degree n)')
    return a, n


def evaluate_polynomial(coefficients: np.ndarray, points: np.ndarray) -> np.ndarray:
    """
    f(x) = m(x)^T a at each point; the degree follows from the coefficient count.

    :param coefficients: (K,) graded_lex coefficients.
    :param points: (N, 3) coordinates in the polynomial's (normalised) frame.
    :returns: (N,) values.
    """
    a, n = _check_coefficients(coefficients)
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.empty(pts.shape[0])
    for s in range(0, pts.shape[0], 65536):
        out[s:s + 65536] = monomial_matrix(pts[s:s + 65536], n) @ a
    return out


def evaluate_polynomial_gradient(coefficients: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Gradient of f at each point, shape (N, 3), in the polynomial's frame."""
    a, n = _check_coefficients(coefficients)
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    out = np.empty((pts.shape[0], 3))
    for s in range(0, pts.shape[0], 65536):
        G = monomial_gradient_matrices(pts[s:s + 65536], n)
        out[s:s + 65536] = np.einsum('apk,k->pa', G, a)
    return out


def coefficient_tensor(coefficients: np.ndarray) -> np.ndarray:
    """Coefficients as a dense tensor A[i, j, k] of shape (n+1, n+1, n+1)."""
    a, n = _check_coefficients(coefficients)
    A = np.zeros((n + 1, n + 1, n + 1))
    E = monomial_exponents(n)
    A[E[:, 0], E[:, 1], E[:, 2]] = a
    return A


def evaluate_polynomial_on_grid(coefficients: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                                zs: np.ndarray) -> np.ndarray:
    """
    Evaluate f on the tensor grid xs x ys x zs by separable contraction (marching-cubes input).

    :returns: array of shape (len(xs), len(ys), len(zs)).
    """
    A = coefficient_tensor(coefficients)
    n = A.shape[0] - 1
    Px = np.vander(np.asarray(xs, float), n + 1, increasing=True)
    Py = np.vander(np.asarray(ys, float), n + 1, increasing=True)
    Pz = np.vander(np.asarray(zs, float), n + 1, increasing=True)
    T = np.einsum('ijk,zk->ijz', A, Pz)
    T = np.einsum('ijz,yj->iyz', T, Py)
    return np.einsum('iyz,xi->xyz', T, Px)
