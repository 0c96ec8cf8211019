"""
Incremental Gram-Schmidt QR for the degree-adaptive implicit-polynomial fit (Section 5).

Eq. 22 solves the least-squares system ``M a = b`` through ``M = QR`` as ``R a = Q^T b`` by back
substitution. When the degree rises, the monomials of the new degree are appended to ``M`` as
one block of columns; Gram-Schmidt works from left to right, so every column of ``Q`` and ``R``
already computed is reused and only the new block is orthogonalised (the shaded part of
Fig. 14).

``variant='arnoldi'`` (the fitter's default; monomial columns of given points): columns are not
orthogonalised as the raw monomials but as ``x_axis * q_parent`` - the previous degree's
orthonormal column of the monomial ``m_j / x_axis`` times one coordinate, as in Vandermonde with
Arnoldi (Brubeck, Nakatsukasa & Trefethen 2021). Together with the old columns they span the
same polynomials, and because graded_lex is a monomial order, the monomial coefficients ``T``
of Q's columns (``Q = M T``) stay upper triangular: ``R = T^-1``, the same factorisation as
Gram-Schmidt on the monomials (``a = T Q^T b`` is the back substitution of ``R a = Q^T b``). The
gain is conditioning: a monomial keeps below 1e-3 of its norm off the old span, a candidate
``x q_p`` 0.2-0.8 (benchmark shapes), so one block pass is accurate where monomials need two.
And ``<x q_p, q_i> = <q_p, x q_i> = 0`` for every ``q_i`` of degree ``<= d - 3`` (``x q_i``
has degree ``<= d - 2``), so that pass projects on the two previous degrees only, one degree
block after the other (block modified Gram-Schmidt), then factorises the block. The loss of
orthogonality left against all old columns is estimated with a 4-column Gaussian sketch
(randomised Gram-Schmidt, Balabanov & Grigori 2022) and a second, full pass made when it
exceeds ``orthogonality_tol`` (1e-10). Columns are dropped exactly as in the monomial variants
(same ``|r_jj|`` tests); a candidate that would carry a dropped monomial is replaced by the raw
monomial, so dropped coefficients stay 0.

``variant='classical'``: BCGS2 (Barlow & Smoktunowicz 2013) on the monomial columns in BLAS-3
calls only - project the block off Q, factorise it locally (Cholesky QR, or Householder near
the stability thresholds), project again, Cholesky QR of the nearly orthonormal result; the
block is copied once into Q's preallocated Fortran-order columns and worked on in place. Every
column gets the second pass: each new monomial keeps far less than 1/sqrt(2) of its norm off
the old span (the DGKS test asks for the second pass on all of them). Ill-conditioned blocks
fall back to the column-wise path below.

Column-wise path (``variant='modified'`` and the fallback): the new block is orthogonalised by
block Gram-Schmidt with re-orthogonalisation: the previous
columns of ``Q`` are projected out as BLAS-3 products (``variant='classical'``: all previous
columns in one product, BCGS2; ``'modified'``: the previous degree blocks one after another,
BMGS2), and a second pass is made for every column whose norm fell below 1/sqrt(2) in the first
(the Daniel-Gragg-Kaufman-Stewart criterion; "twice is enough", Giraud et al. 2005). Inside the
block the columns are orthogonalised the same way by recursive halving, so Python loops run
only over groups of at most eight columns.

Stability is watched through R's diagonal (Section 5; its entries bound R's singular values): a
new column is unstable when ``|r_jj|`` is below ``stability_tol`` times the largest column
norm so far (which bounds every ``|r_ii|``), i.e. when it would push the diagonal's condition
estimate past ``1 / stability_tol``. An unstable column is dropped (its coefficient fixed at 0)
or ridge-regularised (Tasdizen et al. 2000; Sahin & Unel 2005) when the system is solved.
Columns whose orthogonal part is below 1e-12 of their own norm are rounding noise and always
dropped.
"""

from __future__ import annotations

import math
from typing import Dict, List, Optional

from ip_modeler.monomials import degree_slice, monomial_count, monomial_shift_indices
import numpy as np
from scipy.linalg import cho_factor, cho_solve, qr, solve_triangular
from scipy.linalg.blas import dgemm, dsyrk, dtrsm
from scipy.linalg.lapack import dpotrf

try:
    from scipy.linalg.lapack import dtrcon
except ImportError:     # SciPy < 1.12 (Ubuntu 24.04 ships 1.11): same estimate, in numpy
    from ip_modeler.trcon import dtrcon

__all__ = ['IncrementalQR', 'STABILIZATION_MODES', 'VARIANTS']

STABILIZATION_MODES = ('drop', 'ridge', 'none')
VARIANTS = ('arnoldi', 'classical', 'modified')
# Column-wise paths: second projection pass when a column keeps less than this fraction of its
# norm (the Daniel-Gragg-Kaufman-Stewart criterion).
DGKS_REORTH_THRESHOLD = 0.7071
_EPS = float(np.finfo(float).eps)
# Columns of the Gaussian sketch that estimates the loss of orthogonality ('arnoldi').
_SKETCH = 4

# A column whose orthogonal part is below this fraction of its norm is rounding noise: it is
# always dropped, whatever the stabilisation mode.
_NOISE_FLOOR = 1e-12
# Blocks of at most this many columns are orthogonalised column by column.
_BASE_COLUMNS = 8


class IncrementalQR:
    """
    Thin QR factorisation ``M P = Q R`` of a matrix grown by appending column blocks.

    ``P`` selects the accepted columns: columns found numerically dependent are dropped and
    their coefficients are zero in :meth:`solve`.

    :param b: right-hand side of the least-squares problem, shape (N,).
    :param stabilization: ``'drop'`` (unstable columns ignored), ``'ridge'`` (unstable columns
        kept and their coefficients ridge-penalised) or ``'none'`` (only exactly dependent
        columns dropped).
    :param stability_tol: a column is unstable when ``|r_jj|`` is below this times the largest
        column norm seen so far.
    :param variant: for any columns, ``'classical'`` projects the new block on all previous
        columns in one product per pass (BCGS2) and ``'modified'`` on the previous blocks one
        after another (BMGS2); with the second pass both are equally stable (Giraud, Langou &
        Rozloznik 2005). For graded_lex monomial columns of ``points``, ``'arnoldi'`` builds
        the same factorisation from the candidates ``x_axis * q_parent`` in one pass (fastest;
        blocks must then be whole degrees, the first one starting at degree 0).
    :param reorth_threshold: column-wise paths: a second projection pass is made for a column
        whose norm falls below this fraction in the first pass (1.0: always twice; 0.0: never).
    :param capacity: initial column capacity (grown as needed).
    :param points: ``'arnoldi'`` only: the (N, 3) points whose monomials are the columns
        (``monomial_matrix(points, degree)``); the appended blocks are used for their column
        norms and as raw columns where a candidate cannot be formed.
    :param orthogonality_tol: ``'arnoldi'`` only: a block gets the second pass when its
        estimated loss of orthogonality against the old columns exceeds this.
    """

    def __init__(self, b: np.ndarray, stabilization: str = 'drop', stability_tol: float = 1e-6,
                 variant: str = 'classical', reorth_threshold: float = DGKS_REORTH_THRESHOLD,
                 capacity: int = 32, points: Optional[np.ndarray] = None,
                 orthogonality_tol: float = 1e-10) -> None:
        if variant not in VARIANTS:
            raise ValueError(f'variant must be one of {VARIANTS}, got {variant!r}')
        self.variant = variant
        if not 0.0 <= reorth_threshold <= 1.0:
            raise ValueError(f'reorth_threshold must be in [0, 1], got {reorth_threshold}')
        self.reorth_threshold = float(reorth_threshold)
        if not 0.0 < orthogonality_tol < 1e-3:
            raise ValueError(f'orthogonality_tol must be in (0, 1e-3), got {orthogonality_tol}')
        self.orthogonality_tol = float(orthogonality_tol)
        # 'arnoldi': largest estimated loss of orthogonality of a block after its first pass
        self.orthogonality_loss_estimate = 0.0
        self._sketch_rng = np.random.default_rng(0)
        self._X: Optional[np.ndarray] = None
        if variant == 'arnoldi':
            if points is None:
                raise ValueError("variant 'arnoldi' needs the points whose monomials are the "
                                 'columns (points=..., shape (N, 3))')
            X = np.asarray(points, dtype=float)
            if X.ndim != 2 or X.shape[1] != 3 or X.shape[0] != np.size(b):
                raise ValueError(f'points must have shape ({np.size(b)}, 3), got {X.shape}')
            if not np.all(np.isfinite(X)):
                raise ValueError('points contain NaN or infinite values')
            self._X = np.asfortranarray(X)
        elif points is not None:
            raise ValueError("points are only used by variant 'arnoldi'")
        self.reorthogonalised = 0  # columns that needed the second projection pass
        if stabilization not in STABILIZATION_MODES:
            raise ValueError(f'stabilization must be one of {STABILIZATION_MODES}, '
                             f'got {stabilization!r}')
        if not 0.0 <= stability_tol < 1.0:
            raise ValueError(f'stability_tol must be in [0, 1), got {stability_tol}')
        self.b = np.ascontiguousarray(b, dtype=float).reshape(-1)
        self.n_rows = self.b.size
        self.stabilization = stabilization
        self.stability_tol = float(stability_tol)
        self._Q = np.empty((self.n_rows, max(1, capacity)), order='F')
        self._R = np.zeros((max(1, capacity), max(1, capacity)))
        self._qtb = np.zeros(max(1, capacity))
        # Arnoldi variant: T[i, p] is the coefficient of monomial i in Q column p (Q = M T, so
        # R = T^-1 over the accepted columns); position[i] is monomial i's Q column or -1.
        self._T = np.zeros((max(1, capacity), max(1, capacity)), order='F')
        self._position = np.full(max(1, capacity), -1, dtype=np.int64)
        self._blocks: List[slice] = []
        self._degree_rank_start: Dict[int, int] = {}  # 'arnoldi': first Q column of a degree
        self.n_columns = 0  # columns offered so far (accepted or not)
        self._rank = 0
        self._ref_norm = 0.0  # largest column norm so far (bounds every |r_ii|)
        self.accepted: List[int] = []  # original column index of each Q column
        self.dropped: List[int] = []
        self.unstable: List[int] = []  # accepted but flagged for ridge regularisation
        self.column_norms: List[float] = []
        # |r_jj| / largest column norm so far, for every offered column
        self.diagonal_ratio: List[float] = []

    # ----------------------------------------------------------------------------- properties
    @property
    def rank(self) -> int:
        """Count the accepted columns (columns of Q)."""
        return self._rank

    @property
    def Q(self) -> np.ndarray:
        """Orthonormal factor, shape (N, rank) (a view)."""
        return self._Q[:, :self.rank]

    @property
    def R(self) -> np.ndarray:
        """
        Upper-triangular factor over the accepted columns, shape (rank, rank).

        A view for the monomial variants; for ``'arnoldi'`` it is computed as ``T^-1`` (the
        inverse of the accumulated monomial coefficients of Q's columns).
        """
        if self.variant == 'arnoldi':
            T = self._accepted_T(self.rank)
            return solve_triangular(T, np.eye(self.rank), lower=False, check_finite=False)
        return self._R[:self.rank, :self.rank]

    @property
    def T(self) -> np.ndarray:
        """
        ``'arnoldi'`` only: monomial coefficients of Q's columns, ``Q = M[:, :n] T``.

        Shape (n_columns, rank); rows of dropped columns are zero, so over the accepted rows T
        is upper triangular and equals ``R^-1``.
        """
        if self.variant != 'arnoldi':
            raise AttributeError("T is kept by variant 'arnoldi' only")
        return self._T[:self.n_columns, :self.rank]

    def _accepted_T(self, k: int) -> np.ndarray:
        cols = np.asarray(self.accepted[:k], dtype=np.int64)
        return self._T[cols, :k]

    @property
    def qtb(self) -> np.ndarray:
        """``Q^T b`` (Eq. 22), shape (rank,)."""
        return self._qtb[:self.rank]

    def condition_estimate(self) -> float:
        """Return max |r_ii| / min |r_ii| over the accepted columns (R's diagonal, Section 5)."""
        if self.rank == 0:
            return float('inf')
        if self.variant == 'arnoldi':
            d = 1.0 / np.abs(np.diag(self._accepted_T(self.rank)))  # diag(R) = 1 / diag(T)
        else:
            d = np.abs(np.diag(self.R))
        return float(d.max() / d.min()) if d.min() > 0 else float('inf')

    # -------------------------------------------------------------------------------- growth
    def _reserve(self, extra: int) -> None:
        need = self.n_columns + extra  # >= rank + extra
        cap = self._Q.shape[1]
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        Q = np.empty((self.n_rows, new_cap), order='F')
        Q[:, :self.rank] = self._Q[:, :self.rank]
        R = np.zeros((new_cap, new_cap))
        R[:self.rank, :self.rank] = self._R[:self.rank, :self.rank]
        qtb = np.zeros(new_cap)
        qtb[:self.rank] = self.qtb
        T = np.zeros((new_cap, new_cap), order='F')
        T[:self.n_columns, :self.rank] = self._T[:self.n_columns, :self.rank]
        position = np.full(new_cap, -1, dtype=np.int64)
        position[:self.n_columns] = self._position[:self.n_columns]
        self._Q, self._R, self._qtb, self._T, self._position = Q, R, qtb, T, position

    def append(self, block: np.ndarray) -> np.ndarray:
        """
        Append a block of columns (e.g. all monomials of the next degree) and factorise it.

        :param block: (N, m) new columns of M.
        :returns: boolean mask (m,) of the columns accepted into Q.
        :raises ValueError: on a wrong row count or non-finite values.
        """
        B = np.asarray(block, dtype=float)
        if B.ndim == 1:
            B = B[:, None]
        if B.ndim != 2 or B.shape[0] != self.n_rows:
            raise ValueError(f'block has shape {B.shape}, the factorisation has '
                             f'{self.n_rows} rows')
        m = B.shape[1]
        if self.variant == 'arnoldi':
            degrees = self._whole_degrees(m)
        self._reserve(m)
        k0 = self.rank
        if self.variant == 'arnoldi':
            W = B  # only read: the new columns are generated from the points
        else:
            # the block is copied straight into Q's free columns (Fortran order), worked on there
            W = self._Q[:, k0:k0 + m]
            W[...] = B
        norms = np.sqrt(np.einsum('ij,ij->j', W, W))
        if not np.all(np.isfinite(norms)):
            if not np.all(np.isfinite(W)):
                raise ValueError('block contains NaN or infinite values')
            raise ValueError('block column norms overflow (values too large)')
        if m:
            self._ref_norm = max(self._ref_norm, float(norms.max()))
        if self.variant == 'arnoldi':
            first = self.n_columns
            masks = []
            for d in degrees:
                local = slice(degree_slice(d).start - first, degree_slice(d).stop - first)
                masks.append(self._append_arnoldi_degree(d, B[:, local], norms[local]))
            return np.concatenate(masks) if masks else np.zeros(0, dtype=bool)
        if self.variant == 'classical' and m:
            mask = self._append_bcgs2(W, norms)
            if mask is not None:
                return mask
        W = np.array(B, dtype=float, order='F', copy=True)
        # C[p, j]: coefficient of new column j on Q column p (R's new column, Eq. 22).
        C = np.zeros((k0 + m, m))
        if k0:
            self._project(W, slice(0, k0), C, norms, np.arange(m))
        status = np.zeros(m, dtype=np.int8)  # 1 accepted, 2 accepted + unstable, -1 dropped
        positions = np.full(m, -1, dtype=np.int64)
        self._orthogonalise_block(W, norms, C, 0, m, status, positions)
        accepted_mask = status > 0
        for j in range(m):
            col = self.n_columns + j
            self.column_norms.append(float(norms[j]))
            if status[j] < 0:
                self.dropped.append(col)
                continue
            pos = positions[j]
            self._R[:pos, pos] = C[:pos, j]
            self.accepted.append(col)
            if status[j] == 2:
                self.unstable.append(col)
        new = slice(k0, self.rank)
        if self.rank > k0:
            self._blocks.append(new)
            self._qtb[new] = self._Q[:, new].T @ self.b
        self.n_columns += m
        return accepted_mask

    def _whole_degrees(self, m: int) -> List[int]:
        """Degrees covered by a block of ``m`` columns appended now (``'arnoldi'`` only)."""
        def count(d: int) -> int:
            return monomial_count(d) if d >= 0 else 0

        first = 0
        while count(first - 1) < self.n_columns:
            first += 1
        last = first - 1
        while count(last) < self.n_columns + m:
            last += 1
        if count(first - 1) != self.n_columns or count(last) != self.n_columns + m or m == 0:
            raise ValueError(f"variant 'arnoldi' appends whole degrees of graded_lex monomials: "
                             f'{m} columns after {self.n_columns} do not end a degree')
        return list(range(first, last + 1))

    def _arnoldi_candidates(self, degree: int, raw: np.ndarray, dropped: np.ndarray,
                            V: np.ndarray, TV: np.ndarray, lead: np.ndarray,
                            B: np.ndarray) -> None:
        """
        Generate the degree's new columns: ``x_axis * q_parent`` or the raw monomial.

        Column j of the degree is monomial ``m_j = x_axis * m_p``; when ``m_p`` has a Q column
        ``q_p = sum_i T[i, p] m_i``, the candidate is ``x_axis * q_p`` with monomial
        coefficients ``T[i, p]`` moved to ``x_axis * m_i``. Because graded_lex is a monomial
        order (``m_i`` before ``m_p`` implies ``x m_i`` before ``x m_p``), its leading monomial
        is ``m_j`` (coefficient ``T[p, p]``) and T stays triangular. A parent whose shifted
        coefficients would reach a dropped monomial is not used (dropped columns keep
        coefficient 0), and without a usable parent the raw monomial column is taken.
        """
        c0 = self.n_columns
        m = V.shape[1]
        lowered, raised = monomial_shift_indices(degree)
        TV[...] = 0.0
        js = c0 + np.arange(m)
        if degree > 0 and not dropped.any() and not raw.any():
            # nothing dropped so far: every parent has a Q column; one vectorised step
            axis = np.argmax(lowered[:, js] >= 0, axis=0)
            pos = self._position[lowered[axis, js]]
            np.multiply(self._Q[:, pos], self._X[:, axis], out=V)
            TV[raised[axis, :c0].T, np.arange(m)] = self._T[:c0, pos]
            lead[:] = self._T[lowered[axis, js], pos]
            return
        for c in range(m):
            j = c0 + c
            if not raw[c]:
                for axis in range(3):
                    p = lowered[axis, j]
                    if p < 0 or self._position[p] < 0:
                        continue
                    pos = self._position[p]
                    t = self._T[:p + 1, pos]
                    rows = np.flatnonzero(t)
                    targets = raised[axis, rows]
                    if dropped[targets].any():
                        continue
                    np.multiply(self._X[:, axis], self._Q[:, pos], out=V[:, c])
                    TV[targets, c] = t[rows]
                    lead[c] = t[p]
                    break
                else:
                    raw[c] = True
            if raw[c]:
                V[:, c] = B[:, c]
                TV[j, c] = 1.0
                lead[c] = 1.0

    def _append_arnoldi_degree(self, degree: int, B: np.ndarray,
                               norms: np.ndarray) -> np.ndarray:
        """
        Append the monomials of one degree by Arnoldi-style block Gram-Schmidt.

        The new columns are ``x_axis * q_parent`` (see :meth:`_arnoldi_candidates`): with
        the old columns they span the same space as the monomials, but keep a large part of
        their norm off the old span (0.2-0.8 on the benchmark shapes, against below 1e-3 for
        raw monomials), so one block Gram-Schmidt pass (Cholesky QR of the block, Householder
        QR when a column is near the stability or rank thresholds) is accurate. The pass
        projects on the two previous degrees only (exact arithmetic makes the rest zero),
        degree d-2 first, then d-1 (modified Gram-Schmidt order over the blocks);
        the loss of orthogonality against all old columns is then estimated by a Gaussian
        sketch and a second, full pass is made only when it exceeds ``orthogonality_tol``.
        The monomial coefficients of the new Q columns are updated alongside (``Q = M T``),
        and the monomial diagonal ``|r_jj| = h_jj / |T[p, p]|`` (``h_jj``: the norm of the
        candidate off everything before it) drives the same stability and dropping tests as
        the monomial variants.
        """
        m = B.shape[1]
        c0, k0 = self.n_columns, self._rank
        Qo = self._Q[:, :k0]
        To = self._T[:c0, :k0]
        ref = self._ref_norm if self._ref_norm > 0 else 1.0
        dropped = np.zeros(c0 + m, dtype=bool)
        dropped[np.asarray(self.dropped, dtype=np.int64)] = True
        raw = np.zeros(m, dtype=bool)
        V = self._Q[:, k0:k0 + m]
        TV = np.zeros((c0 + m, m), order='F')
        lead = np.ones(m)
        nz_norms = np.where(norms > 0, norms, 1.0)
        while True:
            self._arnoldi_candidates(degree, raw, dropped, V, TV, lead, B)
            before = np.sqrt(np.einsum('ij,ij->j', V, V))
            before = np.where(before > 0, before, 1.0)
            # x * q_p (q_p of degree d-1) is orthogonal to every column of degree <= d-3 in
            # exact arithmetic (<x q_p, q_i> = <q_p, x q_i>, and x q_i has degree <= d-2), so
            # the first pass projects on the two previous degrees only, one degree block after
            # the other (block modified Gram-Schmidt); what rounding leaves on the older
            # columns is part of the measured loss below. Raw monomials need all columns.
            w0 = 0 if raw.any() else self._degree_rank_start.get(degree - 2, 0)
            mid = self._degree_rank_start.get(degree - 1, k0)
            bounds = [w0, mid, k0] if w0 < mid < k0 else [w0, k0]
            for lo, hi in zip(bounds, bounds[1:]):
                if hi > lo:
                    Qw = self._Q[:, lo:hi]
                    H1 = dgemm(1.0, Qw, V, trans_a=True)
                    dgemm(-1.0, Qw, H1, beta=1.0, c=V, overwrite_c=True)
                    TV[:c0] -= self._T[:c0, lo:hi] @ H1
            status = np.ones(m, dtype=np.int8)

            def tests(cols: np.ndarray, d: np.ndarray):
                r = d / np.abs(lead[cols])  # monomial |r_jj|
                return d / before[cols], r / ref, r / nz_norms[cols]

            ratios = np.zeros(m)
            R1, info = dpotrf(dsyrk(1.0, V, trans=1), lower=0, clean=1, overwrite_a=1)
            householder = True
            if info == 0:
                sine, ratio, rho = tests(np.arange(m), np.abs(np.diag(R1)))
                householder = not (sine.min() > 1e-5 and rho.min() > 1e3 * _NOISE_FLOOR
                                   and ratio.min() > 2.0 * self.stability_tol)
            if householder:
                if 0 < w0:
                    # decisions near the thresholds: finish the pass on the older columns so
                    # that no rounding leftover there is mistaken for a new direction
                    Qa = self._Q[:, :w0]
                    H0 = dgemm(1.0, Qa, V, trans_a=True)
                    dgemm(-1.0, Qa, H0, beta=1.0, c=V, overwrite_c=True)
                    TV[:c0] -= self._T[:c0, :w0] @ H0
                cols = list(range(m))
                while cols:
                    Qh, R1 = qr(V[:, cols], mode='economic', check_finite=False)
                    sine, ratio, rho = tests(np.asarray(cols), np.abs(np.diag(R1)))
                    unstable = ratio < self.stability_tol
                    bad = ((sine < _NOISE_FLOOR) | (rho < _NOISE_FLOOR)
                           | (unstable & (self.stabilization == 'drop')))
                    if bad.any():
                        first_bad = int(np.flatnonzero(bad)[0])
                        status[cols[first_bad]] = -1
                        ratios[cols[first_bad]] = ratio[first_bad]
                        del cols[first_bad]
                        continue
                    status[cols] = np.where(unstable & (self.stabilization == 'ridge'), 2, 1)
                    break
                keep = np.asarray(cols, dtype=np.int64)
            else:
                keep = np.arange(m)
            lost = c0 + np.flatnonzero(status < 0)
            contaminated = keep[np.any(TV[lost][:, keep] != 0.0, axis=0)] if lost.size else []
            if len(contaminated) == 0:
                break
            # a kept candidate carries a monomial just dropped: take those columns raw, again
            dropped[lost] = True
            raw[contaminated] = True
        mk = keep.size
        if mk:
            new = slice(k0, k0 + mk)
            target = self._Q[:, new]
            TVk = np.asfortranarray(TV[:, keep])
            if householder:
                sign = np.where(np.diag(R1) < 0, -1.0, 1.0)
                Q1 = np.asfortranarray(Qh * sign)
                R1 = np.asfortranarray(R1 * sign[:, None])
            else:
                Q1 = dtrsm(1.0, R1, V, side=1, lower=0, overwrite_b=1)  # Q1 = V R1^-1
            TVk = dtrsm(1.0, R1, TVk, side=1, lower=0, overwrite_b=1)
            # Loss of orthogonality against the old columns, ||Qo^T Q1||_F, estimated from a
            # Gaussian sketch (E[||G^T E||_F^2] = s ||E||_F^2; randomised Gram-Schmidt,
            # Balabanov & Grigori 2022) at s/m of the cost of the product itself; and the
            # Cholesky QR's own loss inside the block, about eps * cond(R1)^2.
            cross = 0.0
            if k0:
                G = self._sketch_rng.standard_normal((k0, _SKETCH))
                Z = np.asfortranarray(Qo @ G)
                cross = float(np.linalg.norm(dgemm(1.0, Z, Q1, trans_a=True))
                              / math.sqrt(_SKETCH))
            # (LAPACK's 1-norm condition estimate of the triangular factor)
            within = 0.0 if householder else _EPS / max(dtrcon(R1)[0],
                                                        _EPS) ** 2
            self.orthogonality_loss_estimate = max(self.orthogonality_loss_estimate, cross,
                                                   within)
            if cross > self.orthogonality_tol:
                H2 = dgemm(1.0, Qo, Q1, trans_a=True)
                Q1 = dgemm(-1.0, Qo, H2, beta=1.0, c=Q1, overwrite_c=True)
                TVk[:c0] -= To @ H2
                self.reorthogonalised += mk
            if cross > self.orthogonality_tol or within > self.orthogonality_tol:
                R2, info = dpotrf(dsyrk(1.0, Q1, trans=1), lower=0, clean=1, overwrite_a=1)
                if info != 0:
                    raise np.linalg.LinAlgError(
                        f'degree {degree}: re-orthogonalised block is not of full rank')
                Q1 = dtrsm(1.0, R2, Q1, side=1, lower=0, overwrite_b=1)
                TVk = dtrsm(1.0, R2, TVk, side=1, lower=0, overwrite_b=1)
            if not np.shares_memory(Q1, target) or mk < m:
                target[...] = Q1
            self._T[:c0 + m, new] = TVk
            self._qtb[new] = target.T @ self.b
            self._position[c0 + keep] = np.arange(k0, k0 + mk)
            # exact monomial diagonal: R = T^-1 over the accepted columns, r_jj = 1 / t_jj
            ratios[keep] = 1.0 / np.abs(TVk[c0 + keep, np.arange(mk)]) / ref
            self._blocks.append(new)
            self._rank = k0 + mk
        self._degree_rank_start[degree] = k0
        return self._record_columns(norms, ratios, status)

    def _record_columns(self, norms: np.ndarray, ratios: np.ndarray,
                        status: np.ndarray) -> np.ndarray:
        """Bookkeeping of an appended block in column order; returns the accepted mask."""
        for j in range(status.size):
            col = self.n_columns + j
            self.column_norms.append(float(norms[j]))
            self.diagonal_ratio.append(float(ratios[j]))
            if status[j] < 0:
                self.dropped.append(col)
                continue
            self.accepted.append(col)
            if status[j] == 2:
                self.unstable.append(col)
        self.n_columns += status.size
        return status > 0

    def _append_bcgs2(self, W: np.ndarray, norms: np.ndarray) -> Optional[np.ndarray]:
        """
        Block classical Gram-Schmidt with one re-orthogonalisation (BCGS2), BLAS-3 only.

        Barlow & Smoktunowicz (2013): ``W1 = (I - Q Q^T) W``, ``W1 = Q1 R1`` (local Householder
        QR; ``Q1 = W1 R1^-1``), ``W2 = (I - Q Q^T) Q1`` and ``W2 = Q2 R2`` (Cholesky QR, exact
        here because ``W2`` is orthonormal up to ``eps * cond(W1)``); the block's new columns
        of R are ``Q^T W = H1 + H2 R1`` and the diagonal block ``R2 R1``. The second pass is
        made for every column: with monomials the DGKS criterion asks for it on all of them
        anyway (a new monomial keeps far less than 1/sqrt(2) of its norm off the old span).
        ``|r_jj|`` of the local QR is the norm of column j off everything before it, so the
        stability test and dropping are those of column-wise Gram-Schmidt; a dropped column
        is removed and the local QR repeated on the rest.

        :returns: the accepted-column mask, or ``None`` (nothing changed) when the block is
            too ill-conditioned for the Cholesky step; the caller then falls back to the
            column-wise path.
        """
        n, m = W.shape
        k0 = self._rank
        Q = self._Q[:, :k0]
        if k0:
            H1 = dgemm(1.0, Q, W, trans_a=True)
            dgemm(-1.0, Q, H1, beta=1.0, c=W, overwrite_c=True)
        else:
            H1 = np.zeros((0, m))
        status = np.ones(m, dtype=np.int8)
        ratios = np.zeros(m)
        # Fast local factorisation: Cholesky QR of W1 (accurate enough as a first pass when
        # the block is well conditioned, the second pass makes it exact: CholQR2, Yamamoto
        # et al. 2015). Blocks that are ill-conditioned or have a column near the stability
        # thresholds take the Householder route, whose |r_jj| are accurate for the test.
        R1, info = dpotrf(dsyrk(1.0, W, trans=1), lower=0, clean=1, overwrite_a=1)
        d = np.abs(np.diag(R1)) if info == 0 else np.zeros(m)
        ref = self._ref_norm if self._ref_norm > 0 else 1.0
        safe = (info == 0 and d.min() > 1e-5 * d.max() and d.min() > 1e-5 * norms.max()
                and d.min() > 2.0 * self.stability_tol * ref)
        if safe:
            keep = np.arange(m)
            ratios[:] = d / ref
        else:
            cols = list(range(m))
            while cols:
                R1 = qr(W[:, cols], mode='r', check_finite=False)[0][:len(cols)]
                d = np.abs(np.diag(R1))
                ratios[cols] = d / ref if self._ref_norm > 0 else 0.0
                nc = norms[cols]
                rho = np.where(nc > 0, d / np.where(nc > 0, nc, 1.0), 0.0)
                unstable = ratios[cols] < self.stability_tol
                bad = (rho < _NOISE_FLOOR) | (unstable & (self.stabilization == 'drop'))
                if bad.any():
                    j = int(np.flatnonzero(bad)[0])
                    status[cols[j]] = -1
                    del cols[j]
                    continue
                status[cols] = np.where(unstable & (self.stabilization == 'ridge'), 2, 1)
                break
            keep = np.asarray(cols, dtype=np.int64)
            if keep.size:
                if d.min() < 1e-10 * d.max():
                    return None  # local condition too high for the Cholesky step
                R1 = np.array(R1 * np.sign(np.diag(R1))[:, None], order='F')
        mk = keep.size
        if mk:
            new = slice(k0, k0 + mk)
            target = self._Q[:, new]
            Q1 = W if mk == m else np.asfortranarray(W[:, keep])
            Q1 = dtrsm(1.0, R1, Q1, side=1, lower=0, overwrite_b=1)  # Q1 = W1 R1^-1
            if k0:
                H2 = dgemm(1.0, Q, Q1, trans_a=True)
                Q1 = dgemm(-1.0, Q, H2, beta=1.0, c=Q1, overwrite_c=True)
            R2, info = dpotrf(dsyrk(1.0, Q1, trans=1), lower=0, clean=1, overwrite_a=1)
            if info != 0 or np.abs(np.diag(R2) - 1.0).max() > 1e-3:
                return None  # Q1 far from orthonormal: the block was too ill-conditioned
            Q2 = dtrsm(1.0, R2, Q1, side=1, lower=0, overwrite_b=1)  # Q2 = W2 R2^-1
            if not np.shares_memory(Q2, target) or mk < m:
                target[...] = Q2
            if k0:
                self._R[:k0, new] = H1[:, keep] + H2 @ R1
            self._R[new, new] = R2 @ R1
            self._qtb[new] = Q2.T @ self.b
            self._blocks.append(new)
            self._rank = k0 + mk
            self.reorthogonalised += mk
        return self._record_columns(norms, ratios, status)

    def _project(self, W: np.ndarray, rows: slice, C: np.ndarray, norms: np.ndarray,
                 cols: np.ndarray) -> None:
        """
        Project columns ``cols`` of W off Q[:, rows] (BLAS-3), re-orthogonalising as needed.

        The second pass runs on the columns whose norm fell below ``reorth_threshold`` times
        their norm before the pass (the DGKS criterion): there the first pass's rounding error,
        about eps * ||w_before||, is no longer small relative to what is left.
        """
        if cols.size == 0:
            return
        contiguous = cols[-1] - cols[0] + 1 == cols.size
        Wc = W[:, cols[0]:cols[-1] + 1] if contiguous else W[:, cols]
        before = np.sqrt(np.einsum('ij,ij->j', Wc, Wc))
        for it in range(2):
            if self.variant == 'modified':
                blocks = [b for b in self._blocks if b.start >= rows.start and b.stop <= rows.stop]
                if rows.stop > (blocks[-1].stop if blocks else rows.start):
                    blocks.append(slice(blocks[-1].stop if blocks else rows.start, rows.stop))
            else:
                blocks = [rows]
            contiguous = cols[-1] - cols[0] + 1 == cols.size
            Wc = W[:, cols[0]:cols[-1] + 1] if contiguous else W[:, cols]
            for blk in blocks:
                Qb = self._Q[:, blk]
                H = Qb.T @ Wc
                Wc -= Qb @ H
                C[blk.start:blk.stop, cols] += H
            if not contiguous:
                W[:, cols] = Wc
            after = np.sqrt(np.einsum('ij,ij->j', Wc, Wc))
            need = after < self.reorth_threshold * before
            self.reorthogonalised += int(np.count_nonzero(need)) if it == 0 else 0
            if it == 0:
                cols = cols[need]
                before = after[need]
                if cols.size == 0:
                    return

    def _orthogonalise_block(self, W: np.ndarray, norms: np.ndarray, C: np.ndarray, lo: int,
                             hi: int, status: np.ndarray, positions: np.ndarray) -> None:
        """
        Orthogonalise columns lo:hi of W among themselves (already orthogonal to old Q).

        Recursive halving keeps the work in BLAS-3 products: the left half is factorised, the
        right half is projected on the left half's accepted columns twice, then factorised.
        Accepted columns are written to Q in order, with their diagonal entry of R.
        """
        if hi - lo <= _BASE_COLUMNS:
            start = self.rank
            thr = self.reorth_threshold
            for j in range(lo, hi):
                v = W[:, j]
                p = self._rank - start
                r = math.sqrt(float(v @ v))
                if p:
                    Qn = self._Q[:, start:self._rank]
                    for _ in range(2):
                        g = Qn.T @ v
                        v -= Qn @ g
                        C[start:self._rank, j] += g
                        after = math.sqrt(float(v @ v))
                        done = after >= thr * r
                        r = after
                        if done:
                            break
                rho = r / norms[j] if norms[j] > 0 else 0.0  # sine to the previous span
                ratio = r / self._ref_norm if self._ref_norm > 0 else 0.0
                self.diagonal_ratio.append(ratio)
                unstable = ratio < self.stability_tol
                if rho < _NOISE_FLOOR or (unstable and self.stabilization == 'drop'):
                    status[j] = -1
                    continue
                pos = self.rank
                self._Q[:, pos] = v / r
                self._R[pos, pos] = r
                status[j] = 2 if (unstable and self.stabilization == 'ridge') else 1
                positions[j] = pos
                self._rank += 1
            return
        mid = (lo + hi) // 2
        start = self.rank
        self._orthogonalise_block(W, norms, C, lo, mid, status, positions)
        if self.rank > start:
            self._project(W, slice(start, self.rank), C, norms, np.arange(mid, hi))
        self._orthogonalise_block(W, norms, C, mid, hi, status, positions)

    # --------------------------------------------------------------------------------- solve
    def solve(self, n_columns: Optional[int] = None, ridge: float = 0.0) -> np.ndarray:
        """
        Least-squares coefficients of the first ``n_columns`` offered columns (Eq. 22).

        Solves ``R a = Q^T b`` by back substitution over the accepted columns; dropped columns
        get coefficient 0. Regularisation (ridge regression, RR: Tasdizen et al. 2000; Sahin &
        Unel 2005) adds ``sum_j (w_j * s * a_j)^2`` with ``s`` the largest column norm so far
        and ``w_j = stability_tol`` for the unstable columns in ``'ridge'`` mode (partial RR)
        and ``w_j = sqrt(ridge)`` for every column but the first (global RR); it is solved as a
        small stacked least-squares problem on R, so the factorisation is still reused.

        :param n_columns: number of leading columns (default: all offered so far). Because
            columns are appended left to right, any earlier degree can be solved again.
        :param ridge: global ridge weight (>= 0, relative to the squared column scale).
        :returns: coefficients, shape (n_columns,).
        """
        n = self.n_columns if n_columns is None else int(n_columns)
        if not 0 <= n <= self.n_columns:
            raise ValueError(f'n_columns must be in [0, {self.n_columns}], got {n}')
        if ridge < 0 or not np.isfinite(ridge):
            raise ValueError(f'ridge must be finite and >= 0, got {ridge}')
        k = int(np.searchsorted(np.asarray(self.accepted, dtype=np.int64), n))
        a = np.zeros(n)
        if k == 0:
            return a
        y = self._qtb[:k]
        cols = np.asarray(self.accepted[:k], dtype=np.int64)
        w = np.zeros(k)
        if ridge > 0:
            w[cols > 0] = np.sqrt(ridge)
        if self.unstable:
            unstable = np.isin(cols, np.asarray(self.unstable, dtype=np.int64))
            w[unstable] = np.maximum(w[unstable], self.stability_tol)
        if self.variant == 'arnoldi':
            T = self._accepted_T(k)
            if not np.any(w > 0):
                a[cols] = T @ y  # T = R^-1: the back substitution is done
                return a
            R = solve_triangular(T, np.eye(k), lower=False, check_finite=False)
        else:
            R = self._R[:k, :k]
        if np.any(w > 0) and w[w > 0].min() >= 1e-3:
            # normal equations of the stacked problem: the ridge keeps cond <= k / min(w)^2
            A = R.T @ R
            A[np.diag_indices(k)] += (w * self._ref_norm) ** 2
            coef = cho_solve(cho_factor(A, check_finite=False), R.T @ y, check_finite=False)
        elif np.any(w > 0):
            rows = np.flatnonzero(w > 0)
            P = np.zeros((rows.size, k))
            P[np.arange(rows.size), rows] = w[rows] * self._ref_norm
            A = np.vstack([R, P])
            rhs = np.concatenate([y, np.zeros(rows.size)])
            coef = np.linalg.lstsq(A, rhs, rcond=None)[0]
        else:
            coef = solve_triangular(R, y, lower=False, check_finite=False)
        a[cols] = coef
        return a

    def residual_norm(self, n_columns: Optional[int] = None) -> float:
        """``||M a - b||`` of the plain (unregularised) solution over ``n_columns`` columns."""
        n = self.n_columns if n_columns is None else int(n_columns)
        k = int(np.searchsorted(np.asarray(self.accepted, dtype=np.int64), n))
        bb = float(self.b @ self.b)
        return float(np.sqrt(max(bb - float(self._qtb[:k] @ self._qtb[:k]), 0.0)))
