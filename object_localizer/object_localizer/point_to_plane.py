"""
Point-to-plane ICP with a Tukey M-estimator, compiled (numba): the tracker's inner loop.

The same iteration as Open3D's ``registration_icp`` with ``TransformationEstimationPointToPlane
(TukeyLoss(k))`` (which the tracker used before), at a fraction of its cost for the tracker's
small problems (a few thousand scene points against a few thousand model samples):

* correspondences: for every source point the nearest target point within ``reach`` (exact:
  two uniform grids of the target are built once per call; the fine one's 3x3x3 cells around
  the point settle points on the surface, the coarse one is searched in shells of cells until
  no nearer point can exist; a point found farther than ``reach`` is searched again only once
  it has moved enough to come within it), instead of a KD-tree search per point;
* one Gauss-Newton step per iteration: residual ``r = (p - q) . n_q``, Jacobian
  ``[p x n_q, n_q]``, Tukey weight ``(1 - (r / k)^2)^2`` for ``|r| <= k`` (else 0), the 6x6
  normal equations solved and the step applied as ``Rz(c) Ry(b) Rx(a)`` with its translation;
* rotations about ``locked_rotations`` (directions of the target's continuous symmetry axes:
  a torus's or cylinder's axis, every direction for a sphere) are left out of the step: a turn
  about a symmetry axis changes no point-to-plane residual of the exact surface, so the normal
  equations are singular there and, on a sampled surface with noisy points, the step along
  it is noise (a torus spun by 10-40 mrad per iteration, back and forth, and never met the
  stopping tests). The step is solved in the complement (the normal equations projected onto
  it, the locked directions pinned to 0): the same fit of the observable motion, no turn
  about the axis (its small-angle component is 0; applying it as ``Rz Ry Rx`` leaves a
  second-order one, ~1e-5 rad for a 0.03 rad step), and the stopping tests see the
  converged observable step;
* stop when the inlier fraction ("fitness") and the inlier RMS distance both change by less
  than ``tolerance`` (Open3D's criterion), when the step is below ``min_step`` (rotation [rad]
  and translation [m]), when the correspondences are those of two
  iterations back (a two-cycle between two poses a few micrometres apart), or after
  ``max_iterations``.

Points are (N, 3) float64 [m] in one frame; the result is the 4x4 transform that moves the
source onto the target.
"""

from __future__ import annotations

from typing import Optional, Tuple

import numba
import numpy as np

__all__ = ['icp_point_to_plane']


@numba.njit(cache=True)
def _build_grid(P, cell):  # pragma: no cover - numba
    n = P.shape[0]
    lo = np.empty(3)
    dims = np.empty(3, np.int64)
    for a in range(3):
        lo[a] = P[:, a].min()
        dims[a] = int(np.floor((P[:, a].max() - lo[a]) / cell)) + 1
    keys = np.empty(n, np.int64)
    for i in range(n):
        ix = int((P[i, 0] - lo[0]) / cell)
        iy = int((P[i, 1] - lo[1]) / cell)
        iz = int((P[i, 2] - lo[2]) / cell)
        keys[i] = (ix * dims[1] + iy) * dims[2] + iz
    order = np.argsort(keys, kind='mergesort')
    start = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        start[keys[i] + 1] += 1
    for c in range(1, start.shape[0]):
        start[c] += start[c - 1]
    return lo, dims, start, order


@numba.njit(cache=True)
def _nearest(q0, q1, q2, P, lo, dims, start, order, cell, reach,
             limit):  # pragma: no cover - numba
    """
    Find the nearest point of P within ``reach`` of q.

    Index of the nearest point of P within ``reach`` of q (-1: none) and its squared
    distance; -2 when ``limit`` shells of cells do not settle it.
    """
    cx = int(np.floor((q0 - lo[0]) / cell))
    cy = int(np.floor((q1 - lo[1]) / cell))
    cz = int(np.floor((q2 - lo[2]) / cell))
    shells = int(np.ceil(reach / cell))
    best = -1
    bd2 = reach * reach
    for r in range(min(shells, limit) + 1):
        for dx in range(-r, r + 1):
            ix = cx + dx
            if ix < 0 or ix >= dims[0]:
                continue
            ex = dx == -r or dx == r
            for dy in range(-r, r + 1):
                iy = cy + dy
                if iy < 0 or iy >= dims[1]:
                    continue
                edge = ex or dy == -r or dy == r
                dz = -r
                while dz <= r:
                    iz = cz + dz
                    if iz >= 0 and iz < dims[2]:
                        c = (ix * dims[1] + iy) * dims[2] + iz
                        for s in range(start[c], start[c + 1]):
                            j = order[s]
                            d0 = P[j, 0] - q0
                            d1 = P[j, 1] - q1
                            d2 = P[j, 2] - q2
                            d = d0 * d0 + d1 * d1 + d2 * d2
                            if d < bd2:
                                bd2 = d
                                best = j
                    # inside the shell's faces only the two z ends are new
                    if edge or r == 0:
                        dz += 1
                    else:
                        dz += 2 * r
        if best >= 0 and bd2 <= (r * cell) * (r * cell):
            return best, bd2     # every point not yet searched is farther than r cells
    if limit < shells:
        return -2, bd2
    return best, bd2


@numba.njit(cache=True)
def _correspond(S, P, fine, coarse, reach, idx, far, moved):  # pragma: no cover - numba
    """
    Find the nearest target point within ``reach`` of every source point.

    Nearest target point within ``reach`` of every source point: in the fine grid's
    3x3x3 cells around the point when that settles it (points on the surface), else in the
    coarse grid (points farther away); fitness, inlier RMS, count.

    ``far[i]``: a lower bound of point i's distance to the target when last searched (0:
    unknown), ``moved[i]``: how far it has moved since. A point still farther than ``reach``
    by that bound is not searched (no correspondence, exactly); the coarse search looks
    ``reach`` beyond ``reach`` to bound the distance of the points it does not match.
    """
    lo, dims, start, order, cell = fine
    clo, cdims, cstart, corder, ccell = coarse
    count = 0
    sq = 0.0
    for i in range(S.shape[0]):
        if far[i] - moved[i] > reach:
            idx[i] = -1
            continue
        j, d2 = _nearest(S[i, 0], S[i, 1], S[i, 2], P, lo, dims, start, order, cell, reach, 1)
        if j == -2:
            j, d2 = _nearest(S[i, 0], S[i, 1], S[i, 2], P, clo, cdims, cstart, corder, ccell,
                             2.0 * reach, 1 << 30)
        if j >= 0 and d2 > reach * reach:
            far[i] = np.sqrt(d2)          # within 2 reach: its distance
            moved[i] = 0.0
            j = -1
        elif j < 0:
            far[i] = 2.0 * reach          # beyond 2 reach
            moved[i] = 0.0
        else:
            far[i] = 0.0
        idx[i] = j
        if j >= 0:
            count += 1
            sq += d2
    fitness = count / max(S.shape[0], 1)
    rmse = np.sqrt(sq / count) if count > 0 else 0.0
    return fitness, rmse, count


@numba.njit(cache=True)
def _solve6(A, b):  # pragma: no cover - numba
    """
    Solve A x = b for x.

    x with A x = b (6x6, Gaussian elimination with partial pivoting); ok False if
    singular.
    """
    M = A.copy()
    x = b.copy()
    for c in range(6):
        p = c
        for r in range(c + 1, 6):
            if abs(M[r, c]) > abs(M[p, c]):
                p = r
        if abs(M[p, c]) < 1e-18:
            return x, False
        if p != c:
            for k in range(6):
                M[c, k], M[p, k] = M[p, k], M[c, k]
            x[c], x[p] = x[p], x[c]
        for r in range(c + 1, 6):
            f = M[r, c] / M[c, c]
            for k in range(c, 6):
                M[r, k] -= f * M[c, k]
            x[r] -= f * x[c]
    for c in range(5, -1, -1):
        s = x[c]
        for k in range(c + 1, 6):
            s -= M[c, k] * x[k]
        x[c] = s / M[c, c]
    return x, True


@numba.njit(cache=True)
def _step_matrix(x):  # pragma: no cover - numba
    ca, sa = np.cos(x[0]), np.sin(x[0])
    cb, sb = np.cos(x[1]), np.sin(x[1])
    cg, sg = np.cos(x[2]), np.sin(x[2])
    T = np.eye(4)
    # Rz(gamma) Ry(beta) Rx(alpha)
    T[0, 0] = cg * cb
    T[0, 1] = cg * sb * sa - sg * ca
    T[0, 2] = cg * sb * ca + sg * sa
    T[1, 0] = sg * cb
    T[1, 1] = sg * sb * sa + cg * ca
    T[1, 2] = sg * sb * ca - cg * sa
    T[2, 0] = -sb
    T[2, 1] = cb * sa
    T[2, 2] = cb * ca
    T[0, 3] = x[3]
    T[1, 3] = x[4]
    T[2, 3] = x[5]
    return T


@numba.njit(cache=True)
def _lock(A, g, L):  # pragma: no cover - numba
    """
    Project the normal equations onto the steps without rotation about the rows of ``L``.

    ``L``: (K, 3) orthonormal rotation directions (K <= 3). With ``Z = I - E E^T`` (E: the
    rows of L in the rotation block), returns ``(Z A Z + s E E^T, Z g)``, s = trace(A) / 6:
    its solution x has ``E^T x = 0`` exactly and minimises the residuals over those steps.
    """
    Z = np.eye(6)
    for m in range(L.shape[0]):
        for a in range(3):
            for b in range(3):
                Z[a, b] -= L[m, a] * L[m, b]
    A2 = Z @ A @ Z
    g2 = Z @ g
    s = 0.0
    for a in range(6):
        s += A[a, a]
    s = max(s / 6.0, 1e-12)
    for m in range(L.shape[0]):
        for a in range(3):
            for b in range(3):
                A2[a, b] += s * L[m, a] * L[m, b]
    return A2, g2


@numba.njit(cache=True)
def _icp(S0, P, N, fine_cell, cell, reach, k, max_iterations, tolerance,
         min_step, min_residual_step, locked):  # pragma: no cover - numba
    lo, dims, start, order = _build_grid(P, fine_cell)
    fine = (lo, dims, start, order, fine_cell)
    lo, dims, start, order = _build_grid(P, cell)
    coarse = (lo, dims, start, order, cell)
    S = S0.copy()
    n = S.shape[0]
    idx = np.empty(n, np.int64)
    before = np.full(n, -2, np.int64)      # the correspondences two iterations back
    last = np.full(n, -2, np.int64)
    T = np.eye(4)
    far = np.zeros(n)
    moved = np.zeros(n)
    fitness, rmse, count = _correspond(S, P, fine, coarse, reach, idx, far, moved)
    iterations = 0
    J = np.empty(6)
    for _ in range(max_iterations):
        if count == 0:
            break
        A = np.zeros((6, 6))
        g = np.zeros(6)
        wsum = 0.0
        for i in range(n):
            j = idx[i]
            if j < 0:
                continue
            px, py, pz = S[i, 0], S[i, 1], S[i, 2]
            nx, ny, nz = N[j, 0], N[j, 1], N[j, 2]
            r = (px - P[j, 0]) * nx + (py - P[j, 1]) * ny + (pz - P[j, 2]) * nz
            if abs(r) > k:
                continue
            u = 1.0 - (r / k) ** 2
            w = u * u
            wsum += w
            J[0] = py * nz - pz * ny
            J[1] = pz * nx - px * nz
            J[2] = px * ny - py * nx
            J[3], J[4], J[5] = nx, ny, nz
            for a in range(6):
                wa = w * J[a]
                g[a] += wa * r
                for b in range(a, 6):
                    A[a, b] += wa * J[b]
        for a in range(6):
            for b in range(a):
                A[a, b] = A[b, a]
        if locked.shape[0] > 0:
            A_locked, g_locked = _lock(A, g, locked)
            x, ok = _solve6(A_locked, -g_locked)
        else:
            x, ok = _solve6(A, -g)
        if not ok:
            break
        # weighted RMS change of the point-to-plane residuals the step makes (x' A x / sum w):
        # the step along the directions the correspondences observe; a slide along a symmetry
        # (a torus turning about its axis, a cylinder about its own) changes none of them
        q = 0.0
        for a in range(6):
            for b in range(6):
                q += x[a] * A[a, b] * x[b]
        residual_step = np.sqrt(max(q, 0.0) / wsum) if wsum > 0.0 else 0.0
        U = _step_matrix(x)
        T = U @ T
        for i in range(n):
            px, py, pz = S[i, 0], S[i, 1], S[i, 2]
            S[i, 0] = U[0, 0] * px + U[0, 1] * py + U[0, 2] * pz + U[0, 3]
            S[i, 1] = U[1, 0] * px + U[1, 1] * py + U[1, 2] * pz + U[1, 3]
            S[i, 2] = U[2, 0] * px + U[2, 1] * py + U[2, 2] * pz + U[2, 3]
            if far[i] > 0.0:
                moved[i] += np.sqrt((S[i, 0] - px) ** 2 + (S[i, 1] - py) ** 2
                                    + (S[i, 2] - pz) ** 2)
        iterations += 1
        before[:] = last
        last[:] = idx
        f2, r2, count = _correspond(S, P, fine, coarse, reach, idx, far, moved)
        converged = abs(f2 - fitness) < tolerance and abs(r2 - rmse) < tolerance
        # the same correspondences as two iterations back: a two-cycle (the pose steps back
        # and forth between two states a few tens of micrometres apart); more iterations
        # would only repeat it
        cycle = True
        for i in range(n):
            if idx[i] != before[i]:
                cycle = False
                break
        small = np.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2) < min_step and \
            np.sqrt(x[3] ** 2 + x[4] ** 2 + x[5] ** 2) < min_step
        fitness, rmse = f2, r2
        if converged or small or cycle or residual_step < min_residual_step:
            break
    return T, iterations, fitness, rmse


def icp_point_to_plane(source: np.ndarray, target: np.ndarray, target_normals: np.ndarray,
                       reach: float, loss_scale: float, max_iterations: int = 30,
                       tolerance: float = 1e-6, min_step: float = 1e-6,
                       cell: float = 0.0, fine_cell: float = 0.002,
                       min_residual_step: float = 0.0,
                       locked_rotations: Optional[np.ndarray] = None
                       ) -> Tuple[np.ndarray, int, float, float]:
    """
    Align ``source`` (N, 3) [m] to ``target`` (M, 3) with unit ``target_normals`` (M, 3).

    :param reach: largest correspondence distance [m].
    :param loss_scale: Tukey scale k [m] of the point-to-plane residual.
    :param tolerance: stop when fitness and inlier RMS [m] change by less than this.
    :param min_step: stop when the step's rotation [rad] and translation [m] are both below.
    :param min_residual_step: stop when the step changes the point-to-plane residuals by less
        than this [m] (weighted RMS, ``sqrt(x' A x / sum w)`` with the normal matrix A): the
        step has converged in every direction the correspondences observe; a slide along a
        symmetry of the target (which would otherwise run to ``max_iterations``) does not
        count. 0: off.
    :param locked_rotations: (K, 3) directions [target frame] the step never turns about: the
        target's continuous symmetry axes (one for a torus or cylinder; any three independent
        ones for a sphere: no rotation at all). Orthonormalised here; None or (0, 3): none.
    :param cell: grid cell [m] of the correspondence search (0: ``reach / 2``, at least large
        enough for a grid of <= 2 million cells).
    :param fine_cell: cell [m] of the first, local search (about the target's sample spacing;
        at least large enough for a grid of <= 2 million cells).
    :returns: (4x4 source -> target transform, iterations, fitness, inlier RMS [m]).
    """
    S = np.ascontiguousarray(source, dtype=np.float64)
    P = np.ascontiguousarray(target, dtype=np.float64)
    N = np.ascontiguousarray(target_normals, dtype=np.float64)
    if len(S) == 0 or len(P) == 0:
        return np.eye(4), 0, 0.0, 0.0
    L = np.zeros((0, 3)) if locked_rotations is None else \
        np.asarray(locked_rotations, dtype=np.float64).reshape(-1, 3)
    if len(L):
        # an orthonormal basis of the locked directions (at most 3: every rotation)
        _, sv, Vt = np.linalg.svd(L, full_matrices=False)
        L = np.ascontiguousarray(Vt[sv > 1e-9 * sv[0]])
    extent = float(np.max(P.max(axis=0) - P.min(axis=0)))
    cell = float(cell) if cell > 0 else reach / 2.0
    cell = max(cell, extent / 125.0, 1e-6)
    fine_cell = min(max(float(fine_cell), extent / 125.0, 1e-6), cell)
    T, it, fitness, rmse = _icp(S, P, N, fine_cell, cell, float(reach), float(loss_scale),
                                int(max_iterations), float(tolerance), float(min_step),
                                float(min_residual_step), L)
    return T, int(it), float(fitness), float(rmse)
