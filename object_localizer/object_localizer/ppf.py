"""
Point-pair-feature voting (Drost, Ulrich, Navab & Ilic, CVPR 2010), in numpy + numba.

The model is described by every ordered pair of its oriented sample points (m_r, n_r),
(m_i, n_i): the feature F = (||d||, angle(n_r, d), angle(n_i, d), angle(n_r, n_i)) with
d = m_i - m_r, quantised (``distance_step``, ``angle_bins`` over [0, pi]), indexes a table of
(m_r, alpha_m) entries. alpha_m is the angle of m_i about the x axis once m_r is moved to the
origin and n_r turned onto +x (the local frame T_g(m_r, n_r)).

A scene reference point s_r paired with every scene point s_i within the model diameter looks
up the model pairs with the same feature and votes in a 2-D accumulator over (model point m_r,
rotation alpha = alpha_s - alpha_m about the shared x axis). The accumulator's peak is a pose
``T = T_g(s_r)^-1 R_x(alpha) T_g(m_r)`` (model -> scene). Poses from all reference points are
clustered (translation of the model centre and rotation angle under thresholds) and the
clusters ranked by their summed votes (Drost's pose clustering).

As in the later variants of the method (Hinterstoisser et al. 2016, Vidal et al. 2018) the
scene pairs also vote in the neighbouring alpha bin on the side of the continuous value, which
keeps the peak sharp when the true alpha falls on a bin border.

Frames and units: model points in the model frame, scene points in the sensor optical frame,
metres; poses 4x4 model -> sensor. The feature table is dense: an array of offsets over every
quantised feature value (``n_distance_bins * angle_bins**3`` keys), so a lookup is O(1).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Tuple

import numba
import numpy as np

__all__ = ['PPFModel', 'build_ppf_model', 'ppf_vote', 'cluster_poses']


@dataclass
class PPFModel:
    """
    The hash table of a model's point-pair features (see the module doc).

    :ivar points: (M, 3) sampled model points [m], model frame.
    :ivar normals: (M, 3) their outward unit normals.
    :ivar diameter: largest distance between two model points [m].
    :ivar distance_step: quantisation step of the pair distance [m].
    :ivar angle_bins: bins of each feature angle over [0, pi].
    :ivar alpha_bins: bins of the rotation angle alpha over [-pi, pi).
    :ivar offsets: (K + 1,) start of each feature key's entries.
    :ivar entry_point: (E,) model reference point index of each entry.
    :ivar entry_alpha: (E,) alpha_m [rad] of each entry.
    :ivar frame_rotation: (M, 3, 3) rotation R_g(m_r) of each point's local frame.
    """

    points: np.ndarray
    normals: np.ndarray
    diameter: float
    distance_step: float
    angle_bins: int
    alpha_bins: int
    offsets: np.ndarray
    entry_point: np.ndarray
    entry_alpha: np.ndarray
    frame_rotation: np.ndarray

    @property
    def n_distance_bins(self) -> int:
        return int(np.floor(self.diameter / self.distance_step)) + 1


@numba.njit(cache=True)
def _align_to_x(n):  # pragma: no cover - numba
    """Rotation R with R n = +x (Rodrigues about n x e_x)."""
    R = np.eye(3)
    c = n[0]
    ax = np.array([0.0, n[2], -n[1]])       # n x e_x
    s = np.sqrt(ax[1] * ax[1] + ax[2] * ax[2])
    if s < 1e-9:
        if c < 0:
            R[0, 0] = -1.0
            R[1, 1] = -1.0                  # half turn about z
        return R
    ax = ax / s
    K = np.zeros((3, 3))
    K[0, 1] = -ax[2]
    K[0, 2] = ax[1]
    K[1, 0] = ax[2]
    K[1, 2] = -ax[0]
    K[2, 0] = -ax[1]
    K[2, 1] = ax[0]
    return R + s * K + (1.0 - c) * (K @ K)


@numba.njit(cache=True)
def _frames(N):  # pragma: no cover - numba
    out = np.empty((N.shape[0], 3, 3))
    for i in range(N.shape[0]):
        out[i] = _align_to_x(N[i])
    return out


@numba.njit(cache=True)
def _angle_bin(c, nb):  # pragma: no cover - numba
    if c > 1.0:
        c = 1.0
    elif c < -1.0:
        c = -1.0
    b = int(np.arccos(c) / np.pi * nb)
    return nb - 1 if b >= nb else b


@numba.njit(cache=True)
def _feature_key(p1, n1, p2, n2, dstep, nd, nb):  # pragma: no cover - numba
    d0 = p2[0] - p1[0]
    d1 = p2[1] - p1[1]
    d2 = p2[2] - p1[2]
    dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if dist < 1e-12:
        return -1
    k = int(dist / dstep)
    if k >= nd:
        return -1
    d0 /= dist
    d1 /= dist
    d2 /= dist
    a2 = _angle_bin(n1[0] * d0 + n1[1] * d1 + n1[2] * d2, nb)
    a3 = _angle_bin(n2[0] * d0 + n2[1] * d1 + n2[2] * d2, nb)
    a4 = _angle_bin(n1[0] * n2[0] + n1[1] * n2[1] + n1[2] * n2[2], nb)
    return ((k * nb + a2) * nb + a3) * nb + a4


@numba.njit(cache=True)
def _alpha(Rg, pr, pi):  # pragma: no cover - numba
    v0 = pi[0] - pr[0]
    v1 = pi[1] - pr[1]
    v2 = pi[2] - pr[2]
    y = Rg[1, 0] * v0 + Rg[1, 1] * v1 + Rg[1, 2] * v2
    z = Rg[2, 0] * v0 + Rg[2, 1] * v1 + Rg[2, 2] * v2
    return np.arctan2(z, y)


@numba.njit(cache=True)
def _build_table(P, N, frames, dstep, nd, nb, cap):  # pragma: no cover - numba
    M = P.shape[0]
    n_keys = nd * nb * nb * nb
    keys = np.full(M * M, -1, np.int64)
    for r in range(M):
        for i in range(M):
            if i != r:
                keys[r * M + i] = _feature_key(P[r], N[r], P[i], N[i], dstep, nd, nb)
    full = np.zeros(n_keys, np.int64)
    for q in range(M * M):
        if keys[q] >= 0:
            full[keys[q]] += 1
    counts = np.zeros(n_keys + 1, np.int64)
    for k in range(n_keys):
        counts[k + 1] = min(full[k], cap)
    offsets = np.cumsum(counts)
    seen = np.zeros(n_keys, np.int64)
    fill = offsets[:-1].copy()
    entry_point = np.empty(offsets[-1], np.int32)
    entry_alpha = np.empty(offsets[-1], np.float32)
    for r in range(M):
        for i in range(M):
            key = keys[r * M + i]
            if key < 0:
                continue
            c = seen[key]
            seen[key] += 1
            # keep ``cap`` entries evenly spread over the key's pairs (r-major order)
            if (c + 1) * cap // full[key] == c * cap // full[key]:
                continue
            e = fill[key]
            fill[key] += 1
            entry_point[e] = r
            entry_alpha[e] = _alpha(frames[r], P[r], P[i])
    return offsets, entry_point, entry_alpha


def build_ppf_model(points: np.ndarray, normals: np.ndarray, distance_step: float, *,
                    angle_bins: int = 30, alpha_bins: int = 30,
                    max_entries_per_feature: int = 40) -> PPFModel:
    """
    Feature table of a model sampled at about ``distance_step`` [m] (Drost: 0.05 x the diameter).

    A feature value shared by more than ``max_entries_per_feature`` model pairs (planar
    faces, spheres, cylinders: many pairs look alike) keeps that many, evenly spread over the
    model's reference points: such a feature says little about the pose and would dominate the
    voting time.

    :param points: (M, 3) model samples [m], model frame.
    :param normals: (M, 3) outward normals (normalised here).
    :raises ValueError: shapes, fewer than 3 points, non-positive step or bins.
    """
    P = np.ascontiguousarray(points, dtype=float)
    N = np.asarray(normals, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or N.shape != P.shape:
        raise ValueError(f'points and normals must both be (M, 3), got {P.shape}, {N.shape}')
    if len(P) < 3:
        raise ValueError(f'a PPF model needs at least 3 points, got {len(P)}')
    if not distance_step > 0 or angle_bins < 2 or alpha_bins < 2:
        raise ValueError('distance_step must be > 0 and angle_bins, alpha_bins >= 2')
    N = np.ascontiguousarray(N / np.linalg.norm(N, axis=1, keepdims=True))
    c = P.mean(axis=0)
    diameter = 2.0 * float(np.max(np.linalg.norm(P - c, axis=1)))
    nd = int(np.floor(diameter / distance_step)) + 1
    frames = _frames(N)
    if max_entries_per_feature < 1:
        raise ValueError(f'max_entries_per_feature must be >= 1, got {max_entries_per_feature}')
    offsets, ep, ea = _build_table(P, N, frames, float(distance_step), nd, int(angle_bins),
                                   int(max_entries_per_feature))
    return PPFModel(P, N, diameter, float(distance_step), int(angle_bins), int(alpha_bins),
                    offsets, ep, ea, frames)


@numba.njit(cache=True, parallel=True)
def _vote(S, SN, refs, frames_s, max_dist, dstep, nd, nb, na, offsets, entry_point,
          entry_alpha, n_model, peaks):  # pragma: no cover - numba
    R = refs.shape[0]
    out_point = np.full((R, peaks), -1, np.int64)
    out_alpha = np.zeros((R, peaks))
    out_votes = np.zeros((R, peaks))
    two_pi = 2.0 * np.pi
    for q in numba.prange(R):
        r = refs[q]
        acc = np.zeros((n_model, na), np.float32)
        pr = S[r]
        nr = SN[r]
        Rg = frames_s[r]
        for i in range(S.shape[0]):
            if i == r:
                continue
            d0 = S[i, 0] - pr[0]
            d1 = S[i, 1] - pr[1]
            d2 = S[i, 2] - pr[2]
            if d0 * d0 + d1 * d1 + d2 * d2 > max_dist * max_dist:
                continue
            key = _feature_key(pr, nr, S[i], SN[i], dstep, nd, nb)
            if key < 0:
                continue
            a_s = _alpha(Rg, pr, S[i])
            for e in range(offsets[key], offsets[key + 1]):
                a = a_s - entry_alpha[e]
                x = (a + np.pi) / two_pi * na
                x = x - np.floor(x / na) * na
                b = int(x)
                if b >= na:
                    b = na - 1
                frac = x - b
                m = entry_point[e]
                acc[m, b] += 1.0
                # the neighbouring bin on the side of the continuous value
                if frac > 0.5:
                    acc[m, (b + 1) % na] += 1.0
                else:
                    acc[m, (b - 1) % na] += 1.0
        flat = acc.ravel()
        for k in range(peaks):
            best = np.argmax(flat)
            v = flat[best]
            if v <= 0:
                break
            out_point[q, k] = best // na
            out_alpha[q, k] = (best % na + 0.5) / na * two_pi - np.pi
            out_votes[q, k] = v
            # suppress this peak and its alpha neighbours
            m = best // na
            b = best % na
            for db in range(-1, 2):
                flat[m * na + (b + db) % na] = 0.0
    return out_point, out_alpha, out_votes


def _rot_x(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(a.shape + (3, 3))
    R[..., 0, 0] = 1.0
    R[..., 1, 1] = c
    R[..., 1, 2] = -s
    R[..., 2, 1] = s
    R[..., 2, 2] = c
    return R


def ppf_vote(model: PPFModel, scene_points: np.ndarray, scene_normals: np.ndarray, *,
             reference_stride: int = 5, peaks_per_reference: int = 2,
             seed: int = 0) -> Tuple[np.ndarray, np.ndarray]:
    """
    Pose votes of a scene for ``model``.

    :param scene_points: (S, 3) scene samples [m] at about the model's ``distance_step``.
    :param scene_normals: (S, 3) their unit normals, pointing out of the surface (towards the
        sensor for a visible surface).
    :param reference_stride: every k-th scene point (random order from ``seed``) is a reference.
    :param peaks_per_reference: accumulator peaks kept per reference point.
    :return: poses (H, 4, 4) model -> scene and their votes (H,), H <= references x peaks.
    :raises ValueError: shapes.
    """
    S = np.ascontiguousarray(scene_points, dtype=float)
    SN = np.asarray(scene_normals, dtype=float)
    if S.ndim != 2 or S.shape[1] != 3 or SN.shape != S.shape:
        raise ValueError(f'scene points and normals must both be (S, 3), got {S.shape}, '
                         f'{SN.shape}')
    if len(S) < 2:
        return np.zeros((0, 4, 4)), np.zeros(0)
    SN = np.ascontiguousarray(SN / np.maximum(np.linalg.norm(SN, axis=1, keepdims=True), 1e-12))
    rng = np.random.default_rng(seed)
    refs = np.sort(rng.permutation(len(S))[::max(1, int(reference_stride))]).astype(np.int64)
    frames_s = _frames(SN)
    mp, ma, mv = _vote(S, SN, refs, frames_s, model.diameter, model.distance_step,
                       model.n_distance_bins, model.angle_bins, model.alpha_bins, model.offsets,
                       model.entry_point, model.entry_alpha, len(model.points),
                       int(peaks_per_reference))
    ok = mp >= 0
    ref_idx = np.broadcast_to(refs[:, None], mp.shape)[ok]
    m_idx = mp[ok]
    alpha = ma[ok]
    votes = mv[ok]
    # T = T_g(s_r)^-1 R_x(alpha) T_g(m_r), T_g(p, n) = [R_g, -R_g p]
    Rs = frames_s[ref_idx]
    Rm = model.frame_rotation[m_idx]
    R = np.einsum('nji,njk,nkl->nil', Rs, _rot_x(alpha), Rm)
    t = S[ref_idx] - np.einsum('nij,nj->ni', R, model.points[m_idx])
    T = np.zeros((len(R), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = t
    T[:, 3, 3] = 1.0
    return T, votes


@numba.njit(cache=True)
def _cluster(R, C, V, t_thr, cos_thr):  # pragma: no cover - numba
    """Greedy clustering of poses sorted by votes: cluster id per pose and cluster sums."""
    n = R.shape[0]
    seed_R = np.empty((n, 3, 3))
    seed_c = np.empty((n, 3))
    scores = np.zeros(n)
    sum_R = np.zeros((n, 3, 3))
    sum_c = np.zeros((n, 3))
    m = 0
    t2 = t_thr * t_thr
    for k in range(n):
        hit = -1
        for j in range(m):
            d0 = seed_c[j, 0] - C[k, 0]
            d1 = seed_c[j, 1] - C[k, 1]
            d2 = seed_c[j, 2] - C[k, 2]
            if d0 * d0 + d1 * d1 + d2 * d2 > t2:
                continue
            tr = 0.0
            for a in range(3):
                for b in range(3):
                    tr += seed_R[j, a, b] * R[k, a, b]
            if (tr - 1.0) / 2.0 >= cos_thr:
                hit = j
                break
        if hit < 0:
            hit = m
            seed_R[m] = R[k]
            seed_c[m] = C[k]
            m += 1
        scores[hit] += V[k]
        for a in range(3):
            sum_c[hit, a] += V[k] * C[k, a]
            for b in range(3):
                sum_R[hit, a, b] += V[k] * R[k, a, b]
    return scores[:m], sum_R[:m], sum_c[:m]


def cluster_poses(poses: np.ndarray, votes: np.ndarray, centre: np.ndarray,
                  translation_threshold: float, rotation_threshold: float,
                  max_clusters: int = 50) -> Tuple[np.ndarray, np.ndarray]:
    """
    Greedy pose clustering (Drost).

    Poses in order of votes join the first cluster whose seed pose is within
    ``translation_threshold`` [m] (of the model point ``centre``) and ``rotation_threshold`` [rad];
    a cluster's score is the sum of its members' votes and its pose the vote-weighted mean of its
    members (chordal mean of the rotations, mean of the centre).

    :return: cluster poses (C, 4, 4) and scores (C,), best first, C <= max_clusters.
    """
    if len(poses) == 0:
        return np.zeros((0, 4, 4)), np.zeros(0)
    order = np.argsort(-votes, kind='stable')
    P = poses[order]
    V = np.ascontiguousarray(votes[order], dtype=np.float64)
    R = np.ascontiguousarray(P[:, :3, :3])
    centres = np.ascontiguousarray(np.einsum('nij,j->ni', R, centre) + P[:, :3, 3])
    sc, sum_R, sum_c = _cluster(R, centres, V, float(translation_threshold),
                                float(np.cos(rotation_threshold)))
    best = np.argsort(-sc, kind='stable')[:max_clusters]
    out = np.tile(np.eye(4), (len(best), 1, 1))
    for j, b in enumerate(best):
        U, _, Vt = np.linalg.svd(sum_R[b])
        Rb = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        out[j, :3, :3] = Rb
        out[j, :3, 3] = sum_c[b] / sc[b] - Rb @ centre
    return out, sc[best]
