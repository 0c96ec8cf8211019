"""Outlier frames (tracking failures) excluded by MSAC over minimal frame sets + robust refit.

MSAC (the truncated-quadratic member of the RANSAC/MLESAC family, Torr & Zisserman 2000):
hypotheses are fitted to random minimal frame sets (:data:`~joint_estimator.models.MIN_SAMPLES`)
and scored on all frames by ``sum_t min(chi2_t, threshold)``, where ``chi2_t`` is the
noise-normalised residual of frame t about the model (orientation + position, 6 degrees of
freedom; default threshold the 99.9 % quantile of chi-square with 6 dof). The fit on all frames
is always the first hypothesis, so clean data keep the plain estimate. The best hypothesis' inliers
are refitted with the full model (degeneracy checks included; by default followed by the
maximum-likelihood refinement of :mod:`joint_estimator.refine`) and re-classified until the inlier
set is stable.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from scipy.stats import chi2 as chi2_dist

from joint_estimator.common import DegenerateMotionError, JointType
from joint_estimator.models import DEFAULT_MIN_TRANSLATION_RANGE, fit_model, MIN_SAMPLES
from joint_estimator.refine import is_refinable, refine_model
from joint_estimator.revolute import DEFAULT_MIN_ROTATION_RANGE

__all__ = ['DEFAULT_THRESHOLD', 'frame_chi2', 'robust_fit']

#: Per-frame chi-square above which a frame is an outlier (99.9 % quantile, 6 dof).
DEFAULT_THRESHOLD = float(chi2_dist.ppf(0.999, 6))


def frame_chi2(model, R: np.ndarray, p: np.ndarray, sigma_position: float,
               sigma_rotation: float) -> np.ndarray:
    """Noise-normalised squared residual (N,) of each frame about its projection on ``model``
    (chordal orientation distance ``3 - Tr(hat R R^T)`` ~ squared angle)."""
    R_hat, p_hat, _ = model.project(R, p, sigma_position, sigma_rotation)
    rot = 3.0 - np.einsum('nij,nij->n', R_hat, R)
    pos = np.sum((p_hat - p) ** 2, axis=1)
    return np.maximum(rot, 0.0) / sigma_rotation ** 2 + pos / sigma_position ** 2


def robust_fit(joint_type: JointType, R: np.ndarray, p: np.ndarray, sigma_position: float,
               sigma_rotation: float,
               min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
               min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE,
               threshold: float = DEFAULT_THRESHOLD, confidence: float = 0.99,
               max_iterations: int = 100, min_iterations: int = 10,
               refine: bool = True, rng: Optional[np.random.Generator] = None) -> tuple:
    """Fit ``joint_type`` robustly.

    :param R: (N, 3, 3) orientations; :param p: (N, 3) positions [m].
    :param sigma_position: position noise std [m]; :param sigma_rotation: orientation noise
        std [rad] (both per axis).
    :param threshold: per-frame chi-square above which a frame is rejected.
    :param confidence: RANSAC stopping confidence of having drawn one all-inlier set.
    :param refine: refit axis joints by maximum likelihood (:mod:`joint_estimator.refine`).
    :returns: ``(model, inliers (N,) bool, msac_cost)``.
    :raises ValueError: too few frames; :raises DegenerateMotionError: the inliers' motion does
        not determine the model.
    """
    jt = JointType(joint_type)
    n = R.shape[0]
    m = MIN_SAMPLES[jt]
    if n < m:
        raise ValueError(f'{jt.name.lower()} joint: {n} poses given, at least {m} needed')
    rng = np.random.default_rng(0) if rng is None else rng

    def cost_of(model):
        c2 = frame_chi2(model, R, p, sigma_position, sigma_rotation)
        return float(np.minimum(c2, threshold).sum()), c2

    def iterations_needed(c2):
        w = float(np.mean(c2 < threshold))
        if w >= 1.0:
            return 0
        if w <= 0.0:
            return max_iterations
        return int(np.ceil(np.log(1.0 - confidence) / np.log(1.0 - w ** m)))

    best_cost, best_c2, best_model, needed = np.inf, None, None, max_iterations
    try:
        full = fit_model(jt, R, p, min_rotation_range, min_translation_range)
        best_cost, best_c2 = cost_of(full)
        best_model, needed = full, iterations_needed(best_c2)
    except DegenerateMotionError:
        pass          # outliers can fake (or hide) motion: let the minimal sets decide
    it = 0
    while it < min(max(needed, min_iterations), max_iterations):
        it += 1
        idx = rng.choice(n, size=m, replace=False)
        try:
            hyp = fit_model(jt, R[idx], p[idx], 0.0, 0.0)
        except (DegenerateMotionError, np.linalg.LinAlgError):
            continue
        cost, c2 = cost_of(hyp)
        if cost < best_cost:
            best_cost, best_c2, best_model = cost, c2, hyp
            needed = iterations_needed(c2)
    if best_c2 is None:
        raise DegenerateMotionError(f'{jt.name.lower()} joint: no frame set determines the model')
    inliers = best_c2 < threshold
    model, checked, refined = best_model, False, False
    for _ in range(3):
        if inliers.sum() < m:
            raise DegenerateMotionError(
                f'{jt.name.lower()} joint: only {int(inliers.sum())} frames agree with any model')
        try:
            base = fit_model(jt, R[inliers], p[inliers], min_rotation_range,
                             min_translation_range)
            checked = True
        except DegenerateMotionError:
            if not refine:
                raise
            # the orientation-only fit may have rejected good frames (large position
            # residuals); refine the current model on these frames and re-classify instead
            base, checked = model, False
        if refine and is_refinable(base):   # later rounds start from the previous result
            model = refine_model(model if refined else base, R[inliers], p[inliers],
                                 sigma_position, sigma_rotation)
            refined = True
        else:
            model = base
        best_cost, c2 = cost_of(model)
        new = c2 < threshold
        if np.array_equal(new, inliers) or new.sum() < m:
            break
        inliers, checked = new, False
    if not checked:       # degeneracy test on the final inlier set
        fit_model(jt, R[inliers], p[inliers], min_rotation_range, min_translation_range)
    return model, inliers, best_cost
