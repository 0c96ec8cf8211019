"""
Outlier frames, ambiguous (flipped) poses and the noise scale, estimated together.

MSAC (the truncated-quadratic member of the RANSAC/MLESAC family, Torr & Zisserman 2000):
hypotheses are fitted to random minimal frame sets (:data:`~joint_estimator.models.MIN_SAMPLES`)
and scored on all frames by ``sum_t min(chi2_t, threshold)``, where ``chi2_t`` is the
noise-normalised residual of frame t about the model (orientation + position, 6 degrees of
freedom; default threshold the 99.9 % quantile of chi-square with 6 dof). The fit on all frames
is always the first hypothesis, so clean data keep the plain estimate. The best hypothesis'
inliers are refitted with the full model (degeneracy checks included; by default followed by
the maximum-likelihood refinement of :mod:`joint_estimator.refine`) and re-classified until the
inlier set is stable.

**Candidate poses per frame.** A frame may carry several candidate poses (``(N, K, 3, 3)``
orientations, ``(N, K, 3)`` positions): the measured pose first, then its ambiguous twins
(:mod:`joint_estimator.ambiguity`). Every hypothesis uses, per frame, the candidate with the
smallest residual (a twin is charged ``ln(6 N)``, the BIC's price of a fitted choice), so a
flipped pose whose twin fits the joint is *repaired* rather than rejected; the frames are
reported (``choice != 0``). Minimal sets draw a random candidate per frame.

**Noise scale.** With ``sigma_position`` / ``sigma_rotation`` None, the scales are estimated from
the data: for each hypothesis from the 30 % quantile of its per-frame rotation angles and
position distances (a 3-d Gaussian residual's norm has that quantile at ``1.19 sigma``; the
estimate survives 70 % outliers), the hypothesis cost then
being ``sum_t min(chi2_t, threshold) + 6 N ln(sigma_rot sigma_pos)`` (the -2 log-likelihood of
the truncated Gaussian up to constants, so that a hypothesis cannot win by inflating its
scale); after selection, from the RMS residual of the inliers, corrected for what the joint's
coordinates absorb (:func:`residual_shrinkage`, by simulation) and for the model parameters,
iterated with the inlier classification until both are stable. Given sigmas are used as they are.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

from joint_estimator.common import DegenerateMotionError, JointType
from joint_estimator.models import DEFAULT_MIN_TRANSLATION_RANGE, fit_model, MIN_SAMPLES
from joint_estimator.refine import is_refinable, refine_model
from joint_estimator.revolute import DEFAULT_MIN_ROTATION_RANGE, project_track
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2 as chi2_dist

__all__ = ['DEFAULT_THRESHOLD', 'MEDIAN_NORM_3D', 'MIN_SIGMA_POSITION', 'MIN_SIGMA_ROTATION',
           'RobustFit', 'frame_chi2', 'candidate_residuals', 'line_of_sight_ratio',
           'median_scales', 'rms_scales', 'residual_shrinkage', 'robust_fit']

#: Per-frame chi-square above which a frame is an outlier (99.9 % quantile, 6 dof).
DEFAULT_THRESHOLD = float(chi2_dist.ppf(0.999, 6))
#: Median of the norm of a 3-d standard normal vector (sqrt of chi-square(3)'s median).
MEDIAN_NORM_3D = float(np.sqrt(chi2_dist.ppf(0.5, 3)))
#: Quantile of the residual norms that sets a hypothesis' noise scale (breakdown 70 %).
SCALE_QUANTILE = 0.3
_QUANTILE_NORM_3D = float(np.sqrt(chi2_dist.ppf(SCALE_QUANTILE, 3)))
#: Floors of the estimated noise scales (noise-free data would give zero).
MIN_SIGMA_POSITION = 1e-6
MIN_SIGMA_ROTATION = 1e-6
#: Scales used to pick candidates before any scale is known (only their ratio matters there).
_START_SIGMAS = (0.005, np.deg2rad(2.0))


def _angles_from_chordal(c: np.ndarray) -> np.ndarray:
    """Rotation angle [rad] from the chordal distance ``3 - Tr(R_a R_b^T) = 4 sin^2(a / 2)``."""
    return 2.0 * np.arcsin(np.clip(np.sqrt(np.maximum(c, 0.0)) / 2.0, 0.0, 1.0))


def candidate_residuals(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                        sigma_rotation: float, ray_ratio: float = 1.0,
                        exact: bool = True) -> tuple:
    """
    Rotation angle [rad] and position distance [m] of every candidate about ``model``.

    :param R: (N, K, 3, 3) candidate orientations; :param p: (N, K, 3) candidate positions.
    :param ray_ratio: position noise along the line of sight from B's origin (a camera) over
        the noise across it; the component of the position residual along the line of sight is
        divided by it (whitened distance), 1 = isotropic.
    :returns: ``(rotation (N, K), position (N, K))``.
    """
    n, k = R.shape[:2]
    Rf, pf = R.reshape(n * k, 3, 3), p.reshape(n * k, 3)
    R_hat, p_hat, _ = project_track(model, Rf, pf, sigma_position, sigma_rotation, ray_ratio,
                                    exact)
    rot = _angles_from_chordal(3.0 - np.einsum('nij,nij->n', R_hat, Rf))
    d = p_hat - pf
    if ray_ratio != 1.0:
        v = pf / np.maximum(np.linalg.norm(pf, axis=1), 1e-12)[:, None]
        along = np.einsum('ni,ni->n', d, v)
        d = d + np.outer(along, np.ones(3)) * v * (1.0 / ray_ratio - 1.0)
    pos = np.linalg.norm(d, axis=1)
    return rot.reshape(n, k), pos.reshape(n, k)


def frame_chi2(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
               sigma_rotation: float) -> np.ndarray:
    """
    Noise-normalised squared residual (N,) of each frame about ``model``.

    Noise-normalised squared residual (N,) of each frame (one pose per frame: R (N, 3, 3),
    p (N, 3)) about its projection on ``model`` (isotropic noise).
    """
    rot, pos = candidate_residuals(model, R[:, None], p[:, None], sigma_position,
                                   sigma_rotation)
    return (rot[:, 0] / sigma_rotation) ** 2 + (pos[:, 0] / sigma_position) ** 2


def line_of_sight_ratio(p: np.ndarray, max_ratio: float = 100.0,
                        max_correlation: float = -0.4) -> float:
    """
    Measure the position noise along the line of sight over the noise across it.

    Position noise along the line of sight from B's origin (a camera: depth) over the noise
    across it, measured without any model from the second differences of a densely sampled
    track (``d_t = p_{t-1} - 2 p_t + p_{t+1}``, noise-dominated when the motion per frame is
    smooth): ``sqrt((median (d.v)^2 / 0.455) / (median |d_perp|^2 / 2 / 0.693))`` (the medians
    of chi-square 1 and of chi-square 2 / 2).

    The second differences of white noise have a lag-1 autocorrelation of -2/3, of a smooth
    motion a positive one; unless it is below ``max_correlation`` (the differences are noise)
    the track is too sparse to tell and 1 (isotropic) is returned.

    :param p: (N, 3) positions of A in B [m], in time order. :returns: ratio in [1, max_ratio].
    """
    p = np.asarray(p, dtype=float)
    if p.shape[0] < 8:
        return 1.0
    d = p[:-2] - 2.0 * p[1:-1] + p[2:]
    x, y = d[:-1].ravel(), d[1:].ravel()
    den = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    if den <= 0.0 or float(np.sum(x * y)) / den > max_correlation:
        return 1.0
    v = p[1:-1] / np.maximum(np.linalg.norm(p[1:-1], axis=1), 1e-12)[:, None]
    along2 = np.einsum('ni,ni->n', d, v) ** 2
    across2 = np.maximum(np.sum(d ** 2, axis=1) - along2, 0.0) / 2.0
    den = float(np.median(across2)) / 0.6931
    if den <= 0.0:
        return 1.0
    return float(np.clip(np.sqrt(float(np.median(along2)) / 0.4549 / den), 1.0, max_ratio))


def median_scales(rot: np.ndarray, pos: np.ndarray, quantile: float = SCALE_QUANTILE) -> tuple:
    """
    Robust noise scales ``(sigma_position [m], sigma_rotation [rad])``.

    Robust noise scales ``(sigma_position [m], sigma_rotation [rad])`` from per-frame residual
    norms (each the norm of a 3-d Gaussian vector): their ``quantile`` over the same quantile of
    the norm of a standard 3-d normal vector (the median, 1.538, for 0.5), floored. The default
    0.3 keeps the estimate when up to 70 % of the frames are outliers.
    """
    ref = (_QUANTILE_NORM_3D if quantile == SCALE_QUANTILE
           else float(np.sqrt(chi2_dist.ppf(quantile, 3))))
    return (max(float(np.quantile(pos, quantile)) / ref, MIN_SIGMA_POSITION),
            max(float(np.quantile(rot, quantile)) / ref, MIN_SIGMA_ROTATION))


def rms_scales(rot: np.ndarray, pos: np.ndarray, dof: int, n_params: int) -> tuple:
    """
    Noise scales ``(sigma_position, sigma_rotation)`` from the residual norms of inlier frames.

    RMS per axis, corrected for the ``dof`` joint coordinates per frame and the ``n_params`` model
    parameters fitted (``6 n / (6 n - dof n - n_params)``), floored.
    """
    n = rot.size
    free = max(6 * n - dof * n - n_params, 1)
    f = 6.0 * n / free
    return (max(float(np.sqrt(f * np.sum(pos ** 2) / (3 * n))), MIN_SIGMA_POSITION),
            max(float(np.sqrt(f * np.sum(rot ** 2) / (3 * n))), MIN_SIGMA_ROTATION))


def residual_shrinkage(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
                       sigma_rotation: float, ray_ratio: float = 1.0, replicas: int = 4,
                       seed: int = 0) -> tuple:
    """
    How much of the noise the model's projection absorbs, per component, by simulation.

    Noise of the given scales (positions ``ray_ratio`` times noisier along the line of sight) is
    added to the frames' projections on the model and projected again.

    A joint's coordinates absorb part of the noise (a slide takes a position component, an
    angle takes position or orientation noise depending on which is more precise), so the
    residuals underestimate the noise by a factor that depends on the joint and on the ratio
    of the scales; :func:`robust_fit` divides the residuals' mean square by these factors.

    :returns: ``(position factor, rotation factor)``: mean squared residual over the simulated
        noise's mean square (each in (0, 1]).
    """
    R_hat, p_hat, _ = project_track(model, R, p, sigma_position, sigma_rotation, ray_ratio)
    rng = np.random.default_rng(seed)
    n = R.shape[0]
    R_sim = np.concatenate([Rotation.from_rotvec(rng.normal(0.0, sigma_rotation, (n, 3)))
                            .as_matrix() @ R_hat for _ in range(replicas)])
    p_rep = np.concatenate([p_hat] * replicas)
    e = rng.normal(0.0, sigma_position, p_rep.shape)
    v = p_rep / np.maximum(np.linalg.norm(p_rep, axis=1), 1e-12)[:, None]
    e = e + v * (np.einsum('ni,ni->n', e, v) * (ray_ratio - 1.0))[:, None]
    rot, pos = candidate_residuals(model, R_sim[:, None], (p_rep + e)[:, None], sigma_position,
                                   sigma_rotation, ray_ratio)
    f_p = float(np.mean(pos ** 2)) / (3.0 * sigma_position ** 2)
    f_r = float(np.mean(rot ** 2)) / (3.0 * sigma_rotation ** 2)
    return min(max(f_p, 0.05), 1.0), min(max(f_r, 0.05), 1.0)


@dataclass
class RobustFit:
    """
    Result of :func:`robust_fit`.

    :ivar model: the fitted joint model.
    :ivar inliers: (N,) bool, frames that agree with the model (with their chosen candidate).
    :ivar choice: (N,) int, index of the candidate pose used per frame (0: the measured pose).
    :ivar sigma_position: noise scale [m] used (estimated unless given).
    :ivar sigma_rotation: noise scale [rad] used (estimated unless given).
    :ivar scale_estimated: True when the scales were estimated from the data.
    :ivar cost: MSAC cost of the final model.
    """

    model: object
    inliers: np.ndarray
    choice: np.ndarray
    sigma_position: float
    sigma_rotation: float
    scale_estimated: bool
    cost: float


def robust_fit(joint_type: JointType, R: np.ndarray, p: np.ndarray,
               sigma_position: Optional[float] = None, sigma_rotation: Optional[float] = None,
               min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
               min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE,
               threshold: float = DEFAULT_THRESHOLD, confidence: float = 0.99,
               max_iterations: int = 100, min_iterations: Optional[int] = None,
               refine: bool = True, rng: Optional[np.random.Generator] = None,
               max_rounds: int = 8, ray_ratio: float = 1.0) -> RobustFit:
    """
    Fit ``joint_type`` robustly, choosing one candidate pose per frame.

    :param R: (N, 3, 3) orientations or (N, K, 3, 3) candidate orientations (index 0 the
        measured pose); :param p: (N, 3) or (N, K, 3) positions [m].
    :param sigma_position: position noise std [m] per axis, None to estimate it.
    :param sigma_rotation: orientation noise std [rad] per axis, None to estimate it.
    :param threshold: per-frame chi-square above which a frame is rejected.
    :param confidence: RANSAC stopping confidence of having drawn one all-inlier set.
    :param min_iterations: fewest hypotheses drawn; default 10 with given noise levels and one
        pose per frame, else 50 (an estimated scale makes every hypothesis look mostly
        inlier, so the adaptive stopping rule would stop too early).
    :param max_iterations: most hypotheses drawn.
    :param refine: refit axis joints by maximum likelihood (:mod:`joint_estimator.refine`).
    :param max_rounds: refit / re-classify rounds after the hypothesis search.
    :param ray_ratio: position noise along the line of sight from B's origin over the noise
        across it (:func:`candidate_residuals`); ``sigma_position`` is then the noise across.
    :raises ValueError: too few frames; :raises DegenerateMotionError: the inliers' motion does
        not determine the model.
    """
    jt = JointType(joint_type)
    if R.ndim == 3:
        R, p = R[:, None], p[:, None]
    n, k = R.shape[:2]
    m = MIN_SAMPLES[jt]
    if n < m:
        raise ValueError(f'{jt.name.lower()} joint: {n} poses given, at least {m} needed')
    rng = np.random.default_rng(0) if rng is None else rng
    fix_p, fix_r = sigma_position is not None, sigma_rotation is not None
    estimate = not (fix_p and fix_r)
    rows = np.arange(n)
    # using a twin instead of the measured pose is one more fitted choice per frame: it costs
    # what the BIC charges a parameter (joint_estimator.selection), so a twin is used only
    # where it fits clearly better
    twin_penalty = np.zeros((1, k))
    twin_penalty[0, 1:] = np.log(6.0 * n)
    if min_iterations is None:
        min_iterations = 50 if (estimate or k > 1) else 10

    def with_given(sp, sr):
        return (sigma_position if fix_p else sp, sigma_rotation if fix_r else sr)

    start = with_given(*_START_SIGMAS)

    def evaluate(model, scales=None, exact=True):
        """(cost, chi2 (N,), choice (N,), scales) of a model; scales estimated if None."""
        sp, sr = start if scales is None else scales
        rot, pos = candidate_residuals(model, R, p, sp, sr, ray_ratio, exact)
        if scales is None and estimate:
            choice = np.argmin((rot / sr) ** 2 + (pos / sp) ** 2 + twin_penalty, axis=1)
            sp, sr = with_given(*median_scales(rot[rows, choice], pos[rows, choice]))
        c2 = (rot / sr) ** 2 + (pos / sp) ** 2 + twin_penalty
        choice = np.argmin(c2, axis=1)
        c2 = c2[rows, choice]
        cost = float(np.minimum(c2, threshold).sum())
        if estimate:
            cost += 6.0 * n * float(np.log(sp * sr))
        return cost, c2, choice, (sp, sr), rot[rows, choice], pos[rows, choice]

    def iterations_needed(c2):
        w = float(np.mean(c2 < threshold)) / k        # a random candidate per sampled frame
        if w >= 1.0:
            return 0
        if w <= 0.0:
            return max_iterations
        return int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - w ** m)))

    best, best_model, needed = None, None, max_iterations
    try:
        full = fit_model(jt, R[:, 0], p[:, 0], min_rotation_range, min_translation_range)
        best, best_model = evaluate(full, exact=False), full
        needed = iterations_needed(best[1])
    except DegenerateMotionError:
        pass          # outliers can fake (or hide) motion: let the minimal sets decide
    it = 0
    while it < min(max(needed, min_iterations), max_iterations):
        it += 1
        idx = rng.choice(n, size=m, replace=False)
        pick = rng.integers(0, k, size=m)
        try:
            hyp = fit_model(jt, R[idx, pick], p[idx, pick], 0.0, 0.0)
        except (DegenerateMotionError, np.linalg.LinAlgError):
            continue
        res = evaluate(hyp, exact=False)
        if best is None or res[0] < best[0]:
            best, best_model = res, hyp
            needed = iterations_needed(res[1])
    if best is None:
        raise DegenerateMotionError(f'{jt.name.lower()} joint: no frame set determines the model')
    _, c2, choice, scales, _, _ = best
    inliers = c2 < threshold
    model, checked, refined = best_model, False, False
    for _ in range(max_rounds):
        if inliers.sum() < m:
            raise DegenerateMotionError(
                f'{jt.name.lower()} joint: only {int(inliers.sum())} frames agree with any model')
        R_in, p_in = R[rows, choice][inliers], p[rows, choice][inliers]
        try:
            base = fit_model(jt, R_in, p_in, min_rotation_range, min_translation_range)
            checked = True
        except DegenerateMotionError:
            if not refine:
                raise
            # the orientation-only fit may have rejected good frames (large position
            # residuals); refine the current model on these frames and re-classify instead
            base, checked = model, False
        if refine and is_refinable(base):   # later rounds start from the previous result
            model = refine_model(model if refined else base, R_in, p_in, *scales,
                                 ray_ratio=ray_ratio)
            refined = True
        else:
            model = base
        cost, c2_new, choice_new, _, rot, pos = evaluate(model, scales)
        new_scales = scales
        if estimate:
            ok = c2_new < threshold
            if ok.sum() >= m:
                f_p, f_r = residual_shrinkage(model, R[rows, choice_new][ok],
                                              p[rows, choice_new][ok], *scales, ray_ratio)
                n_ok = int(ok.sum())
                k_corr = 6.0 * n_ok / max(6.0 * n_ok - model.n_params, 1.0)
                new_scales = with_given(
                    max(float(np.sqrt(k_corr * np.mean(pos[ok] ** 2) / (3.0 * f_p))),
                        MIN_SIGMA_POSITION),
                    max(float(np.sqrt(k_corr * np.mean(rot[ok] ** 2) / (3.0 * f_r))),
                        MIN_SIGMA_ROTATION))
                cost, c2_new, choice_new, _, _, _ = evaluate(model, new_scales)
        new = c2_new < threshold
        stable = (np.array_equal(new, inliers) and np.array_equal(choice_new, choice)
                  and np.allclose(new_scales, scales, rtol=0.02))
        scales = new_scales
        if stable or new.sum() < m:
            inliers, choice = (new, choice_new) if new.sum() >= m else (inliers, choice)
            break
        inliers, choice, checked = new, choice_new, False
    if not checked:       # degeneracy test on the final inlier set
        fit_model(jt, R[rows, choice][inliers], p[rows, choice][inliers], min_rotation_range,
                  min_translation_range)
    return RobustFit(model, inliers, choice, float(scales[0]), float(scales[1]), estimate,
                     float(cost))
