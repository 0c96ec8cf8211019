"""
Non-linear vision error correction (step 1 of Section 3; after Takamatsu et al. 2007).

From the observed pose, find a nearby pose of the moving object at which every pair of the
contact relation has zero distance. As the chapter says, any such configuration is accepted:
this step does not care where the correction goes along the unconstrained directions (which it
"often contaminates"); the optimal step (:mod:`.optimal_correction`) removes that.

Method: Gauss-Newton on the signed distances with minimum-norm steps, the Jacobian rows being
Eq. 2 rows ``[p x f, f]`` (exact at contact). Steps are screws ``[w, v]`` applied to the moving
object in the fixed frame, ``x -> R(w) x + v``; the minimum-norm step uses the metric
``|v|^2 + (L |w|)^2`` with ``L`` the moving object's size, so that the result is the feasible
pose closest to the observation in that metric (to first order), ``L`` = a quarter of the
bounding-box diagonal by default. With a ``pivot`` (a point of the moving object) the screws
turn about that point, ``x -> R(w) (x - c) + c + v``: the metric is then the pivot's
displacement and the rotation, independent of where the fixed model's origin is (a push-out,
whose result is this step's, uses the stated pose noise about the correction's reference
point).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from stereo_manip_tools.transforms import rotation_about_axis, rotation_log

from .contact_relation import ContactEvaluator, ContactPair
from .polyhedron import cross3, Polyhedron

__all__ = ['NonlinearResult', 'correct_nonlinear', 'apply_screw', 'constraint_rows',
           'warm_up', 'RESIDUAL_TOLERANCE']

#: The one contact residual tolerance [m] of the package: the non-linear step stops there and
#: every later check (optimal step, acceptance in correct_pose) uses the same value.
RESIDUAL_TOLERANCE = 1e-9


@dataclass
class NonlinearResult:
    """
    Outcome of :func:`correct_nonlinear`.

    :ivar T_rel: corrected pose of the moving object in the fixed frame (4x4).
    :ivar max_residual: largest |distance| of the relation at ``T_rel`` [m].
    :ivar iterations: Gauss-Newton iterations used.
    :ivar converged: True when ``max_residual <= residual_tolerance``.
    """

    T_rel: np.ndarray
    max_residual: float
    iterations: int
    converged: bool


def apply_screw(T: np.ndarray, w: np.ndarray, v: np.ndarray,
                centre: np.ndarray | None = None) -> np.ndarray:
    """
    Move a pose by the finite screw ``x -> R(w) (x - c) + c + v`` in its parent frame.

    :param T: 4x4 pose.
    :param w: rotation vector [rad], shape (3,).
    :param v: translation [m], shape (3,).
    :param centre: (3,) the point ``c`` the rotation turns about [m, parent frame]; None: the
        parent frame's origin.
    """
    angle = float(np.linalg.norm(w))
    Rw = rotation_about_axis(w, angle) if angle > 0 else np.eye(3)
    c = np.zeros(3) if centre is None else np.asarray(centre, dtype=float)
    out = np.eye(4)
    out[:3, :3] = Rw @ T[:3, :3]
    out[:3, 3] = Rw @ (T[:3, 3] - c) + c + v
    return out


def constraint_rows(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Rows ``[p x f, f]`` of Eq. 2 (screw order ``[s0, s1]``), shape (K, 6)."""
    P = np.asarray(points, dtype=float).reshape(-1, 3)
    F = np.asarray(normals, dtype=float).reshape(-1, 3)
    return np.hstack([cross3(P, F), F])


try:  # the compiled iteration (same steps as the Python loop below, which stays the reference)
    import numba

    @numba.njit(cache=True, fastmath=False, error_model='numpy')
    def _rot_about(w: np.ndarray, angle: float) -> np.ndarray:  # pragma: no cover
        """Rotate by angle about w: rotation_about_axis (Rodrigues, axis normalised here)."""
        # scaled first: the squares of a step's components near 1e-160 underflow to 0 (the
        # caller's np.linalg.norm does not), and w / 0 made the iteration NaN (hypothesis
        # found it: cube_on_table observed 5e-153 rad from the contact)
        m = max(abs(w[0]), abs(w[1]), abs(w[2]))
        if m == 0.0:
            return np.eye(3)
        s0, s1, s2 = w[0] / m, w[1] / m, w[2] / m
        n = np.sqrt(s0 * s0 + s1 * s1 + s2 * s2)
        a0, a1, a2 = s0 / n, s1 / n, s2 / n
        K = np.array([[0.0, -a2, a1], [a2, 0.0, -a0], [-a1, a0, 0.0]])
        return np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * (K @ K)

    @numba.njit(cache=True, fastmath=False, error_model='numpy')
    def _rot_log(R: np.ndarray) -> np.ndarray:  # pragma: no cover
        """Return rotation_log of stereo_manip_tools.transforms (same branches)."""
        c = min(max((R[0, 0] + R[1, 1] + R[2, 2] - 1.0) / 2.0, -1.0), 1.0)
        theta = np.arccos(c)
        w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
        if theta < 1e-7:
            return 0.5 * w
        if np.pi - theta < 1e-4:
            B = ((R + R.T) / 2.0 - c * np.eye(3)) / (1.0 - c)
            i = int(np.argmax(np.diag(B)))
            axis = B[:, i] / np.sqrt(max(B[i, i], 1e-300))
            if axis[0] * w[0] + axis[1] * w[1] + axis[2] * w[2] < 0:
                axis = -axis
            return axis / np.linalg.norm(axis) * theta
        return w * (theta / (2.0 * np.sin(theta)))

    @numba.njit(cache=True, fastmath=False, error_model='numpy')
    def _evaluate(T, vf, vf_x, vf_n, vf_off, fv, fv_w, fv_n, fv_off, ee, ee_a, ee_em, ee_b,
                  ee_ef, ee_sg, d, P, N):  # pragma: no cover
        """Evaluate like ContactEvaluator.__call__ into d, P, N; -1 or the parallel ee row."""
        R = T[:3, :3]
        t = T[:3, 3]
        for j in range(len(vf)):
            k = vf[j]
            acc = 0.0
            for i in range(3):
                x = R[i, 0] * vf_x[j, 0] + R[i, 1] * vf_x[j, 1] + R[i, 2] * vf_x[j, 2] + t[i]
                P[k, i] = x
                N[k, i] = vf_n[j, i]
                acc += vf_n[j, i] * x
            d[k] = acc - vf_off[j]
        for j in range(len(fv)):
            k = fv[j]
            nm = np.empty(3)
            for i in range(3):
                nm[i] = R[i, 0] * fv_n[j, 0] + R[i, 1] * fv_n[j, 1] + R[i, 2] * fv_n[j, 2]
            off = fv_off[j] + (nm[0] * t[0] + nm[1] * t[1] + nm[2] * t[2])
            d[k] = (nm[0] * fv_w[j, 0] + nm[1] * fv_w[j, 1] + nm[2] * fv_w[j, 2]) - off
            for i in range(3):
                P[k, i] = fv_w[j, i]
                N[k, i] = -nm[i]
        bad, smin = -1, np.inf
        for j in range(len(ee)):
            k = ee[j]
            a = np.empty(3)
            em = np.empty(3)
            for i in range(3):
                a[i] = R[i, 0] * ee_a[j, 0] + R[i, 1] * ee_a[j, 1] + R[i, 2] * ee_a[j, 2] + t[i]
                em[i] = R[i, 0] * ee_em[j, 0] + R[i, 1] * ee_em[j, 1] + R[i, 2] * ee_em[j, 2]
            ef = ee_ef[j]
            c0 = em[1] * ef[2] - em[2] * ef[1]
            c1 = em[2] * ef[0] - em[0] * ef[2]
            c2 = em[0] * ef[1] - em[1] * ef[0]
            s = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            if s < 1e-9 and s < smin:
                bad, smin = j, s
            n0, n1, n2 = ee_sg[j] * c0 / s, ee_sg[j] * c1 / s, ee_sg[j] * c2 / s
            w0, w1, w2 = a[0] - ee_b[j, 0], a[1] - ee_b[j, 1], a[2] - ee_b[j, 2]
            d[k] = n0 * w0 + n1 * w1 + n2 * w2
            B = em[0] * ef[0] + em[1] * ef[1] + em[2] * ef[2]
            u = ((ef[0] * w0 + ef[1] * w1 + ef[2] * w2)
                 - B * (em[0] * w0 + em[1] * w1 + em[2] * w2)) / (1.0 - B * B)
            for i in range(3):
                P[k, i] = ee_b[j, i] + u * ef[i]
            N[k, 0], N[k, 1], N[k, 2] = n0, n1, n2
        return bad

    @numba.njit(cache=True, fastmath=False, error_model='numpy')
    def _iterate(T_obs, K, vf, vf_x, vf_n, vf_off, fv, fv_w, fv_n, fv_off, ee, ee_a, ee_em,
                 ee_b, ee_ef, ee_sg, L, schedule, max_iterations, residual_tolerance,
                 rcond, pivot, use_pivot):  # pragma: no cover
        """Run the loop of correct_nonlinear: (T_best, res_best, it_best, parallel ee row)."""
        T = T_obs.copy()
        c_obs = np.ascontiguousarray(T_obs[:3, :3]) @ pivot + T_obs[:3, 3]
        scale = np.array([1.0 / L, 1.0 / L, 1.0 / L, 1.0, 1.0, 1.0])
        d = np.zeros(K)
        P = np.zeros((K, 3))
        N = np.zeros((K, 3))
        T_best = T.copy()
        res_best = np.inf
        it_best = 0
        have_best = False
        it = 0
        eps = np.finfo(np.float64).eps
        Ro = T_obs[:3, :3]
        for mu in schedule:
            have_first = False
            first = 0.0
            n_it = max_iterations if mu == 0.0 else min(max_iterations, 8)
            for _ in range(n_it):
                bad = _evaluate(T, vf, vf_x, vf_n, vf_off, fv, fv_w, fv_n, fv_off, ee, ee_a,
                                ee_em, ee_b, ee_ef, ee_sg, d, P, N)
                if bad >= 0:
                    return T_best, res_best, it_best, bad
                res = np.max(np.abs(d))
                if mu == 0.0 and (not have_best or res < res_best):
                    T_best, res_best, it_best, have_best = T.copy(), res, it, True
                if mu == 0.0 and res <= 1e-3 * residual_tolerance:
                    break
                # the screw's centre: the pivot where it is now, else the fixed origin
                c = np.zeros(3)
                if use_pivot:
                    c = np.ascontiguousarray(T[:3, :3]) @ pivot + T[:3, 3]
                J = np.empty((K, 6))
                for k in range(K):
                    p0, p1, p2 = P[k, 0] - c[0], P[k, 1] - c[1], P[k, 2] - c[2]
                    J[k, 0] = (p1 * N[k, 2] - p2 * N[k, 1]) * scale[0]
                    J[k, 1] = (p2 * N[k, 0] - p0 * N[k, 2]) * scale[1]
                    J[k, 2] = (p0 * N[k, 1] - p1 * N[k, 0]) * scale[2]
                    J[k, 3] = N[k, 0]
                    J[k, 4] = N[k, 1]
                    J[k, 5] = N[k, 2]
                if mu > 0.0:
                    e = np.empty(6)
                    e[:3] = L * _rot_log(np.ascontiguousarray(T[:3, :3])
                                         @ np.ascontiguousarray(Ro.T))
                    if use_pivot:
                        e[3:] = c - c_obs
                    else:
                        e[3:] = T[:3, 3] - T_obs[:3, 3]
                    Jm = np.zeros((K + 6, 6))
                    Jm[:K] = J
                    rhs = np.empty(K + 6)
                    rhs[:K] = -d
                    for i in range(6):
                        Jm[K + i, i] = mu
                        rhs[K + i] = -mu * e[i]
                    step = np.linalg.lstsq(Jm, rhs, eps * (K + 6))[0]
                else:
                    step = np.linalg.lstsq(J, -d, rcond)[0]
                it += 1
                step = step * scale
                ang = np.sqrt(step[0] ** 2 + step[1] ** 2 + step[2] ** 2)
                if ang > 0.3:
                    step = step * (0.3 / ang)
                w = step[:3]
                angle = np.linalg.norm(w)
                Rw = _rot_about(w, angle) if angle > 0 else np.eye(3)
                Tn = np.eye(4)
                Tn[:3, :3] = Rw @ np.ascontiguousarray(T[:3, :3])
                Tn[:3, 3] = Rw @ (np.ascontiguousarray(T[:3, 3]) - c) + c + step[3:]
                T = Tn
                size = np.linalg.norm(step / scale)
                if not have_first:
                    first, have_first = size, True
                if mu > 0.0 and size < 1e-2 * first:
                    break
        return T_best, res_best, it_best, -1

    _HAVE_NUMBA = True
except ImportError:  # pragma: no cover - numba is in the environment
    _HAVE_NUMBA = False


def warm_up() -> None:
    """
    Compile the iteration now (or load it from numba's disk cache).

    With a cold cache the first compiled call costs ~30 s CPU (once per source tree: the
    bootstrap calls this after a build), loading it from the cache ~0.1 s.
    """
    if not _HAVE_NUMBA:
        return
    z3, z1, i0 = np.zeros((0, 3)), np.zeros(0), np.zeros(0, dtype=np.int64)
    _iterate(np.eye(4), 1, np.zeros(1, dtype=np.int64), np.zeros((1, 3)),
             np.array([[0.0, 0.0, 1.0]]), np.array([-1e-3]), i0, z3, z3, z1, i0, z3, z3, z3,
             z3, z1, 0.1, np.array([3e-2, 0.0]), 5, 1e-9, 1e-6, np.zeros(3), False)


def correct_nonlinear(moving: Polyhedron, fixed: Polyhedron, T_rel_observed: np.ndarray,
                      pairs: Sequence[ContactPair], max_iterations: int = 30,
                      residual_tolerance: float = RESIDUAL_TOLERANCE,
                      length_scale: float | None = None, rcond: float = 1e-6,
                      anchor_schedule: tuple = (3e-2, 3e-3),
                      compiled: bool | None = None,
                      pivot: np.ndarray | None = None) -> NonlinearResult:
    """
    Nearby pose satisfying every contact of ``pairs`` (non-linear step, Takamatsu 2007).

    :param T_rel_observed: observed pose of the moving object in the fixed frame (4x4).
    :param pairs: the contact relation to satisfy.
    :param residual_tolerance: the result is ``converged`` when every |distance| is below
        this [m]; the iteration itself continues to 1e-3 of it (Gauss-Newton converges
        quadratically, so the last steps cost little and leave the optimal step an exact
        start).
    :param length_scale: ``L`` of the step metric [m] (default: a quarter of the moving
        object's bounding-box diagonal, about its radius). A larger ``L`` makes rotations
        expensive and can send the solution to a distant, degenerate configuration (a peg
        just inside a hole pulled up to the rim, where it may tilt).
    :param rcond: relative singular-value cut-off of the final Gauss-Newton steps.
    :param anchor_schedule: decreasing weights of the pull towards the observed pose in the
        Levenberg-Marquardt stages run before Gauss-Newton (scaled units).
    :param max_iterations: iteration limit per stage.
    :param pivot: (3,) a point of the moving object [m, moving model frame]: the steps turn
        about it and their translation is its displacement, so the metric is
        ``|v_pivot|^2 + (L |w|)^2`` and the result is the feasible pose nearest the observation
        in it (with ``L`` = sigma_translation / sigma_rotation about the point the pose errors
        turn about: nearest in stated-noise units, whatever the fixed model's origin). None:
        the fixed frame's origin (the chapter's step: where the result goes along the free
        directions does not matter, the optimal step sets it).
    :param compiled: run the iteration compiled (numba; the same steps, results equal to the
        Python loop's to rounding); None: when numba is available. False: the Python loop
        (the reference).
    :returns: the corrected pose; ``converged`` is False when the relation could not be
        satisfied within the iteration limit (e.g. a relation that no pose realises).
    """
    T_obs = np.array(T_rel_observed, dtype=float)
    T = T_obs.copy()
    if not pairs:
        return NonlinearResult(T, 0.0, 0, True)
    L = float(length_scale) if length_scale else max(moving.size / 4.0, 1e-6)
    scale = np.array([1.0 / L] * 3 + [1.0] * 3)
    piv = np.zeros(3) if pivot is None else np.asarray(pivot, dtype=float).reshape(3).copy()
    best = None
    it = 0
    evaluate = ContactEvaluator(moving, fixed, pairs)
    if _HAVE_NUMBA if compiled is None else compiled:
        e = evaluate
        z3, z1 = np.zeros((0, 3)), np.zeros(0)
        T_best, res_best, it_best, bad = _iterate(
            T_obs, len(e.pairs), e.vf, getattr(e, 'vf_x', z3), getattr(e, 'vf_n', z3),
            getattr(e, 'vf_off', z1), e.fv, getattr(e, 'fv_w', z3), getattr(e, 'fv_n', z3),
            getattr(e, 'fv_off', z1), e.ee, getattr(e, 'ee_a', z3), getattr(e, 'ee_em', z3),
            getattr(e, 'ee_b', z3), getattr(e, 'ee_ef', z3), e.sg, L,
            np.array(tuple(anchor_schedule) + (0.0,), dtype=float), int(max_iterations),
            float(residual_tolerance), float(rcond), piv, pivot is not None)
        if bad >= 0:
            raise ValueError(f'edge-edge pair ({e.pairs[e.ee[bad]]}) has parallel edges at '
                             'this pose')
        return NonlinearResult(T_best, float(res_best), int(it_best),
                               bool(res_best <= residual_tolerance))
    # Levenberg-Marquardt anchored at the observation, with continuation of the anchor weight
    # mu -> 0, then plain Gauss-Newton. Directions that are free at the solution (sliding
    # along a hole) look weakly constrained at a noisy, tilted pose; the anchor keeps the
    # iterate from drifting along them (to a degenerate configuration) while the well
    # constrained directions converge.
    for mu in tuple(anchor_schedule) + (0.0,):
        first = None
        for k in range(max_iterations if mu == 0.0 else min(max_iterations, 8)):
            g = evaluate(T)
            res = float(np.max(np.abs(g.distances)))
            if mu == 0.0 and (best is None or res < best[1]):
                best = (T.copy(), res, it)
            if mu == 0.0 and res <= 1e-3 * residual_tolerance:
                break       # converged well past the acceptance tolerance (quadratic steps)
            # the screw's centre: the pivot where it is now, else the fixed origin
            c = T[:3, :3] @ piv + T[:3, 3] if pivot is not None else np.zeros(3)
            J = constraint_rows(g.points - c, g.normals) * scale
            if mu > 0.0:
                moved = (c - (T_obs[:3, :3] @ piv + T_obs[:3, 3]) if pivot is not None
                         else T[:3, 3] - T_obs[:3, 3])
                e = np.concatenate([L * rotation_log(T[:3, :3] @ T_obs[:3, :3].T), moved])
                J = np.vstack([J, mu * np.eye(6)])
                rhs = np.concatenate([-g.distances, -mu * e])
                step, *_ = np.linalg.lstsq(J, rhs, rcond=None)
            else:
                # truncated SVD: drop singular values below rcond x the largest
                step, *_ = np.linalg.lstsq(J, -g.distances, rcond=rcond)
            it += 1
            step *= scale
            # damp very large rotation steps (far from the solution)
            ang = np.linalg.norm(step[:3])
            if ang > 0.3:
                step *= 0.3 / ang
            T = apply_screw(T, step[:3], step[3:], centre=c)
            size = float(np.linalg.norm(step / scale))
            first = size if first is None else first
            if mu > 0.0 and size < 1e-2 * first:
                break   # close enough to this stage's anchored optimum
    T_best, res_best, it_best = best
    return NonlinearResult(T_best, res_best, it_best, res_best <= residual_tolerance)
