"""
``np.linalg`` for the small real matrices of the per-frame path, without the per-call overhead.

The scorer and the optimal step decompose thousands of 6x6 and (K, 3) matrices per track; the
public ``np.linalg`` functions spend most of their time on type dispatch around the LAPACK
call. These call the same gufuncs (so the results are the same, bit for bit) for real float64
2-D input; a decomposition that does not converge (NaN output) is handed to ``np.linalg``,
which raises as before. With another numpy the public functions are used.
"""

from __future__ import annotations

from typing import Tuple, Union

import numpy as np

__all__ = ['svd', 'eigvalsh', 'solve']

try:
    from numpy.linalg import _umath_linalg as _um
    _um.svd_f, _um.svd_s, _um.svd, _um.eigvalsh_lo, _um.solve1  # noqa: B018
    _HAVE = True
except (ImportError, AttributeError):  # pragma: no cover - other numpy versions
    _HAVE = False


def svd(a: np.ndarray, full_matrices: bool = True, compute_uv: bool = True
        ) -> Union[np.ndarray, Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Decompose a real float64 (M, N) array as ``np.linalg.svd`` does (same arguments)."""
    a = np.asarray(a, dtype=float)
    if not _HAVE or a.ndim != 2 or a.size == 0:
        return np.linalg.svd(a, full_matrices=full_matrices, compute_uv=compute_uv)
    if not compute_uv:
        s = _um.svd(a, signature='d->d')
        return s if np.isfinite(s).all() else np.linalg.svd(a, compute_uv=False)
    u, s, vh = (_um.svd_f if full_matrices else _um.svd_s)(a, signature='d->ddd')
    if not np.isfinite(s).all():
        return np.linalg.svd(a, full_matrices=full_matrices)
    return u, s, vh


def eigvalsh(a: np.ndarray) -> np.ndarray:
    """Eigenvalues (ascending) of a real symmetric float64 (N, N) array (np.linalg.eigvalsh)."""
    if not _HAVE:
        return np.linalg.eigvalsh(a)
    w = _um.eigvalsh_lo(a, signature='d->d')
    return w if np.isfinite(w).all() else np.linalg.eigvalsh(a)


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve ``a x = b`` as ``np.linalg.solve``: real float64 (N, N) ``a``, (N,) ``b``."""
    if not _HAVE:
        return np.linalg.solve(a, b)
    x = _um.solve1(a, b, signature='dd->d')
    return x if np.isfinite(x).all() else np.linalg.solve(a, b)
