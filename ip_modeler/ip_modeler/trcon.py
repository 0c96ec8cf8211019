"""
Reciprocal condition number of a triangular matrix: LAPACK ``dtrcon`` for SciPy < 1.12.

``scipy.linalg.lapack.dtrcon`` exists from SciPy 1.12; Ubuntu 24.04 ships SciPy 1.11, where the
import fails. :func:`dtrcon` here follows LAPACK's algorithm step by step -- ``dlantr`` for the
norm of ``A``, Higham's ``dlacn2`` estimator (Hager's method with the alternating-sign final
stage, at most 5 iterations) for the norm of ``A^-1`` with triangular solves in place of
``dlatrs`` -- so it returns the same estimate (not the exact condition number), to rounding.
"""

from __future__ import annotations

from typing import Tuple

import numpy as np
from scipy.linalg import solve_triangular

__all__ = ['dtrcon', 'norm1_estimate']

_ITMAX = 5


def _sign(x: np.ndarray) -> np.ndarray:
    """Return LAPACK's sign vector: +1 where x >= 0, else -1."""
    return np.where(x >= 0.0, 1.0, -1.0)


def norm1_estimate(apply, apply_t, n: int) -> float:
    """
    LAPACK ``dlacn2``: lower estimate of ``||A||_1`` from products ``A x`` and ``A^T x``.

    :param apply: ``x -> A @ x`` for shape (n,) vectors.
    :param apply_t: ``x -> A.T @ x``.
    """
    x = apply(np.full(n, 1.0 / n))
    if n == 1:
        return float(abs(x[0]))
    est = float(np.abs(x).sum())
    isgn = _sign(x)
    x = apply_t(isgn)
    j = int(np.argmax(np.abs(x)))
    iteration = 2
    while True:
        x = np.zeros(n)
        x[j] = 1.0
        v = apply(x)
        est_old = est
        est = float(np.abs(v).sum())
        xs = _sign(v)
        if np.array_equal(xs, isgn) or est <= est_old:   # converged, or cycling
            break
        isgn = xs
        x = apply_t(isgn)
        j_last = j
        j = int(np.argmax(np.abs(x)))
        if x[j_last] != abs(x[j]) and iteration < _ITMAX:
            iteration += 1
            continue
        break
    alt = np.where(np.arange(n) % 2 == 0, 1.0, -1.0) * (1.0 + np.arange(n) / (n - 1))
    temp = 2.0 * float(np.abs(apply(alt)).sum()) / (3 * n)
    return max(est, temp)


def dtrcon(a: np.ndarray, norm: str = '1', uplo: str = 'U', diag: str = 'N'
           ) -> Tuple[float, int]:
    """
    ``scipy.linalg.lapack.dtrcon``: ``(rcond, info)`` of the triangular matrix ``a``.

    :param norm: ``'1'``/``'O'`` (1-norm) or ``'I'`` (infinity norm).
    :param uplo: ``'U'`` (upper triangle of ``a`` used) or ``'L'``.
    :param diag: ``'N'`` or ``'U'`` (unit diagonal assumed).
    :returns: reciprocal condition number estimate (0 for a singular matrix) and 0.
    """
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[0] != a.shape[1]:
        raise ValueError(f'dtrcon: expected a square matrix, got shape {a.shape}')
    norm, uplo, diag = norm.upper(), uplo.upper(), diag.upper()
    if norm not in ('1', 'O', 'I') or uplo not in ('U', 'L') or diag not in ('N', 'U'):
        raise ValueError(f'dtrcon: bad option norm={norm!r} uplo={uplo!r} diag={diag!r}')
    n = a.shape[0]
    if n == 0:
        return 1.0, 0
    lower = uplo == 'L'
    t = np.tril(a) if lower else np.triu(a)
    if diag == 'U':
        np.fill_diagonal(t, 1.0)
    one_norm = norm in ('1', 'O')
    a_norm = float(np.abs(t).sum(axis=0 if one_norm else 1).max())        # dlantr
    if not a_norm > 0.0 or np.any(np.diag(t) == 0.0):
        return 0.0, 0

    def solve(x: np.ndarray, trans: int) -> np.ndarray:
        return solve_triangular(t, x, lower=lower, trans=trans, check_finite=False)
    # 1-norm of inv(A): kase 1 multiplies by inv(A); the infinity norm swaps the two products
    apply, apply_t = (lambda x: solve(x, 0)), (lambda x: solve(x, 1))
    if not one_norm:
        apply, apply_t = apply_t, apply
    inv_norm = norm1_estimate(apply, apply_t, n)
    if not np.isfinite(inv_norm) or inv_norm == 0.0:
        return 0.0, 0
    return (1.0 / a_norm) / inv_norm, 0
