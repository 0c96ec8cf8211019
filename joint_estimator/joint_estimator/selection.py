"""Joint estimation with automatic type selection by BIC (as in Sturm et al. 2011).

Each candidate type is fitted (robustly by default, :mod:`joint_estimator.robust`) and scored::

    BIC = sum_{inliers} chi2_t + n_out * c_out + (n_params + dof * n_in) * ln(6 N)

with ``chi2_t`` the frame's noise-normalised residual (6 observed values per frame), ``c_out``
the -2 log-likelihood of a frame under the uniform outlier density of MLESAC's mixture
(:func:`outlier_cost`; at least the rejection threshold), and the joint coordinates of each
inlier frame counted as free parameters (otherwise a 3-dof model always beats a 1-dof one).
Lower is better. Types whose motion is degenerate (e.g. a revolute axis from too small a
rotation range) are not scored; the reason is kept in :attr:`JointEstimation.failures`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Iterable, Optional

import numpy as np

from joint_estimator.common import (
    DegenerateMotionError, JOINT_DOF, JointFit, JointType, split_track, validate_track)
from joint_estimator.models import DEFAULT_MIN_TRANSLATION_RANGE, fit_model, MIN_SAMPLES
from joint_estimator.refine import refine_model
from joint_estimator.revolute import DEFAULT_MIN_ROTATION_RANGE, make_fit
from joint_estimator.robust import DEFAULT_THRESHOLD, robust_fit

__all__ = ['JointEstimation', 'bic_score', 'outlier_cost', 'estimate_joint', 'ALL_TYPES']

ALL_TYPES = tuple(JointType)


@dataclass
class JointEstimation:
    """Result of :func:`estimate_joint`: the selected fit, every candidate and every failure."""

    best: JointFit
    candidates: Dict[JointType, JointFit] = field(default_factory=dict)
    failures: Dict[JointType, str] = field(default_factory=dict)

    @property
    def scores(self) -> Dict[JointType, float]:
        """BIC of every scored candidate (lower is better)."""
        return {t: f.score for t, f in self.candidates.items()}

    @property
    def status(self) -> str:
        """One line: the selection, rejected frames and why other types were not scored."""
        b = self.best
        parts = [f'{b.joint_type.name.lower()} selected (BIC {b.score:.1f})']
        if b.outlier_indices.size:
            parts.append(f'{b.outlier_indices.size} of {b.inliers.size} frames rejected as '
                         'outliers')
        if b.status:
            parts.append(b.status)
        parts += [f'{t.name.lower()} not scored: {msg}' for t, msg in self.failures.items()]
        return '; '.join(parts)


def outlier_cost(sigma_position: float, sigma_rotation: float,
                 workspace_volume: float = 1.0) -> float:
    """-2 log-likelihood of an outlier frame: a pose uniform over a ``workspace_volume`` [m^3]
    region times SO(3) (volume 8 pi^2), against a Gaussian inlier density of the given noise
    levels, i.e. ``2 ln(V 8 pi^2 / ((2 pi)^3 sigma_pos^3 sigma_rot^3))`` (MLESAC's mixture)."""
    return float(2.0 * np.log(workspace_volume * 8.0 * np.pi ** 2 / (
        (2.0 * np.pi) ** 3 * sigma_position ** 3 * sigma_rotation ** 3)))


def bic_score(fit: JointFit, outlier_cost_value: float) -> float:
    """BIC of a fit over all its frames (see the module docstring)."""
    n = fit.chi2.shape[0]
    n_in = int(fit.inliers.sum())
    k = fit.n_params + JOINT_DOF[fit.joint_type] * n_in
    return float(fit.chi2[fit.inliers].sum() + outlier_cost_value * (n - n_in)
                 + k * np.log(6.0 * n))


def estimate_joint(poses: np.ndarray, joint_type: Optional[int] = None,
                   sigma_position: float = 0.005, sigma_rotation: float = np.deg2rad(2.0),
                   robust: bool = True, refine: bool = True, correction: str = 'ml',
                   min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
                   min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE,
                   stamps_ns=None, candidates: Iterable[int] = ALL_TYPES,
                   threshold: float = DEFAULT_THRESHOLD,
                   rng: Optional[np.random.Generator] = None) -> JointEstimation:
    """Estimate the joint between two links from the relative track of A in B.

    :param poses: (N, 4, 4) relative poses ``^B T_A(t)`` [m].
    :param joint_type: a :class:`JointType` to fit only that type, or None (or 255) to select
        among ``candidates`` by BIC.
    :param sigma_position: position noise std [m] per axis.
    :param sigma_rotation: orientation noise std [rad] per axis.
    :param robust: reject outlier frames (MSAC + refit) when True.
    :param refine: refine revolute and cylindrical joints by maximum likelihood over orientations
        and positions (:mod:`joint_estimator.refine`); False gives the chapter's estimate exactly.
    :param correction: ``'ml'`` (default; frames projected on the joint by weighted least
        squares) or ``'chapter'`` (revolute: minimal-rotation correction of Section 4).
    :param min_rotation_range: [rad], :param min_translation_range: [m] below which an axis or a
        sliding direction is reported as undefined (degenerate motion).
    :param stamps_ns: optional (N,) stamps [ns], must increase strictly.
    :raises ValueError: bad input (shape, too few poses, NaN, non-orthonormal rotation,
        stamps), or no candidate type could be fitted (the message lists why).
    """
    if sigma_position <= 0 or sigma_rotation <= 0:
        raise ValueError(f'noise levels must be positive, got sigma_position={sigma_position}, '
                         f'sigma_rotation={sigma_rotation}')
    if joint_type is not None and int(joint_type) != 255:
        types = [JointType(int(joint_type))]
    else:
        types = [JointType(int(t)) for t in candidates]
    # a joint needs motion: at least two poses, and the smallest set of the types asked for
    need = max(2, min(MIN_SAMPLES[t] for t in types))
    T = validate_track(poses, stamps_ns, min_poses=need)
    R, p = split_track(T)
    rng = np.random.default_rng(0) if rng is None else rng
    result = JointEstimation(best=None)
    out_cost = max(threshold, outlier_cost(sigma_position, sigma_rotation))
    for t in types:
        try:
            if robust:
                model, inliers, _ = robust_fit(t, R, p, sigma_position, sigma_rotation,
                                               min_rotation_range, min_translation_range,
                                               threshold, refine=refine, rng=rng)
            else:
                model = fit_model(t, R, p, min_rotation_range, min_translation_range)
                if refine:
                    model = refine_model(model, R, p, sigma_position, sigma_rotation)
                inliers = None
        except (DegenerateMotionError, ValueError) as e:
            result.failures[t] = str(e)
            continue
        fit = make_fit(model, R, p, sigma_position, sigma_rotation, correction, inliers)
        fit.score = bic_score(fit, out_cost)
        result.candidates[t] = fit
    if not result.candidates:
        raise DegenerateMotionError('no joint type could be fitted: ' + '; '.join(
            f'{t.name.lower()}: {m}' for t, m in result.failures.items()))
    result.best = min(result.candidates.values(), key=lambda f: f.score)
    return result
