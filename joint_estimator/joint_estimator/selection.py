"""
Joint estimation with automatic type selection by BIC (as in Sturm et al. 2011).

Each candidate type is fitted (robustly by default, :mod:`joint_estimator.robust`: outlier
frames, flipped marker poses repaired with their ambiguous twin, noise scales estimated from
the data unless given) and scored by its -2 log-likelihood plus the BIC penalty::

    BIC = sum_{inliers} (chi2_t + 6 ln(2 pi s_rot s_pos)) + n_out * c_out
          + (n_params + dof * n_in + n_repaired) * ln(6 N)

with ``chi2_t`` the frame's residual normalised by the type's noise scales ``s_rot``, ``s_pos``
(6 observed values per frame; with estimated scales each type has its own, so a type that fits
worse pays through its larger scales and not through the user's guess of the noise), ``c_out``
the -2 log-likelihood of a frame under the uniform outlier density of MLESAC's mixture
(:func:`outlier_cost`; at least the rejection threshold's), and the joint coordinates of each
inlier frame counted as free parameters (otherwise a 3-dof model always beats a 1-dof one), and
so is the choice of each pose replaced by its ambiguity twin (``n_repaired``).
Lower is better. Types whose motion is degenerate (e.g. a revolute axis from too small a
rotation range) are not scored; the reason is kept in :attr:`JointEstimation.failures`.

The selected fit is then qualified (:func:`qualify_fit`): unwrapped joint coordinates, the span
of the motion covered by inlier frames, the axis uncertainty, and warnings when more than a
third of the frames were rejected or the inliers cover less than half of the motion.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Iterable, Optional

from joint_estimator.ambiguity import relative_candidates
from joint_estimator.common import (
    DegenerateMotionError, frame_residuals, JOINT_DOF, JointFit, JointType, split_track,
    validate_track)
from joint_estimator.marker_noise import (
    corner_angles, estimate_marker_side, marker_corners, MIN_RAY_RATIO, project_marker_corners,
    refine_revolute_corners)
from joint_estimator.models import DEFAULT_MIN_TRANSLATION_RANGE, fit_model, MIN_SAMPLES
from joint_estimator.refine import axis_uncertainty, refine_model
from joint_estimator.revolute import DEFAULT_MIN_ROTATION_RANGE, make_fit
from joint_estimator.robust import (
    _START_SIGMAS, candidate_residuals, DEFAULT_THRESHOLD, line_of_sight_ratio, rms_scales,
    robust_fit)
import numpy as np
from scipy.stats import chi2 as chi2_dist

__all__ = ['JointEstimation', 'bic_score', 'outlier_cost', 'estimate_joint', 'qualify_fit',
           'unwrap_angles', 'ALL_TYPES', 'MAX_REJECTED_FRACTION', 'MIN_COVERAGE']

ALL_TYPES = tuple(JointType)
#: A warning is raised when more than this fraction of the frames is rejected.
MAX_REJECTED_FRACTION = 1.0 / 3.0
#: A warning is raised when the inliers span less than this fraction of the motion.
MIN_COVERAGE = 0.5
#: Corner-space refit of a marker track: a frame is an inlier below this quantile of
#: chi-square with 5 dof (its corner residual over the estimated corner noise).
CORNER_FRAME_QUANTILE = 0.999
#: Corner-space refit: most re-classification rounds.
CORNER_ROUNDS = 3


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
        if b.repaired_indices.size:
            parts.append(f'{b.repaired_indices.size} flipped poses repaired with their '
                         'ambiguous twin')
        parts.append(f'noise {"estimated" if b.scale_estimated else "given"}: '
                     f'{b.sigma_position * 1000:.3g} mm, {np.rad2deg(b.sigma_rotation):.3g} deg')
        if 'corner_noise_normalised' in b.extra:
            parts.append(f'marker fit in the image: corner noise '
                         f'{b.extra["corner_noise_normalised"]:.3g} (normalised; x focal length'
                         f' = px), side {b.extra["marker_side"] * 1000:.0f} mm '
                         f'({"estimated" if b.extra["marker_side_estimated"] else "given"})')
        if np.isfinite(b.coverage):
            unit, f = (('mm', 1000.0) if b.joint_type == JointType.PRISMATIC
                       else ('deg', np.rad2deg(1.0)))
            parts.append(f'inliers cover {(b.coordinate_range[1] - b.coordinate_range[0]) * f:.1f}'
                         f' of {(b.motion_range[1] - b.motion_range[0]) * f:.1f} {unit}')
        if np.isfinite(b.axis_angle_std_in_b):
            parts.append(f'axis std {np.rad2deg(b.axis_angle_std_in_b):.3g} deg, '
                         f'{b.axis_point_std * 1000:.3g} mm')
        parts += [f'WARNING: {w}' for w in b.warnings]
        if b.status:
            parts.append(b.status)
        parts += [f'{t.name.lower()} not scored: {msg}' for t, msg in self.failures.items()]
        return '; '.join(parts)


def outlier_cost(sigma_position: float, sigma_rotation: float,
                 workspace_volume: float = 1.0) -> float:
    """
    -2 log-likelihood of an outlier frame.

    a pose uniform over a ``workspace_volume`` [m^3] region times SO(3) (volume 8 pi^2), against a
    Gaussian inlier density of the given noise levels, i.e. ``2 ln(V 8 pi^2 / ((2 pi)^3 sigma_pos^3
    sigma_rot^3))`` (MLESAC's mixture).
    """
    return float(2.0 * np.log(workspace_volume * 8.0 * np.pi ** 2 / (
        (2.0 * np.pi) ** 3 * sigma_position ** 3 * sigma_rotation ** 3)))


def bic_score(fit: JointFit, outlier_cost_value: float) -> float:
    """
    BIC of a fit over all its frames (see the module docstring).

    :param outlier_cost_value: ``c_out`` relative to an inlier's normalisation, i.e. the
        outlier frame's cost minus ``6 ln(2 pi s_rot s_pos)`` (:func:`outlier_cost` at the
        fit's scales, or larger).
    """
    n = fit.chi2.shape[0]
    n_in = int(fit.inliers.sum())
    k = fit.n_params + JOINT_DOF[fit.joint_type] * n_in
    if fit.repaired is not None:          # each twin used is a fitted choice
        k += int((fit.repaired & fit.inliers).sum())
    norm = 6.0 * np.log(2.0 * np.pi * fit.sigma_position * fit.sigma_rotation)
    return float(fit.chi2[fit.inliers].sum() + n * norm + outlier_cost_value * (n - n_in)
                 + k * np.log(6.0 * n))


def unwrap_angles(q: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """
    Joint angles (N,) [rad] made continuous in frame order.

    The inlier frames are unwrapped among themselves (a rejected frame's angle cannot make them
    jump by 2 pi), every other frame takes the 2 pi branch nearest the inliers' angle interpolated
    at its index.
    """
    q = np.asarray(q, dtype=float)
    idx = np.flatnonzero(inliers)
    if idx.size == 0:
        return np.unwrap(q)
    out = q.copy()
    out[idx] = np.unwrap(q[idx])
    rest = np.flatnonzero(~np.asarray(inliers, bool))
    if rest.size:
        ref = np.interp(rest, idx, out[idx])
        out[rest] = q[rest] + 2.0 * np.pi * np.round((ref - q[rest]) / (2.0 * np.pi))
    return out


def qualify_fit(fit: JointFit, R: np.ndarray, p: np.ndarray, uncertainty: bool = True) -> None:
    """
    Add the honest part of a fit in place.

    Unwrapped angle coordinates, the inliers' span of the motion (``coordinate_range``,
    ``motion_range``, ``coverage``), the axis uncertainty (revolute, cylindrical;
    :func:`joint_estimator.refine.axis_uncertainty` on the inlier frames) and ``warnings``.

    :param R: (N, 3, 3), :param p: (N, 3) [m]: the poses the fit was made from (the candidates
        chosen per frame).
    """
    jt = fit.joint_type
    inl = fit.inliers
    if jt in (JointType.REVOLUTE, JointType.CYLINDRICAL, JointType.PLANAR):
        fit.coordinates = fit.coordinates.copy()
        fit.coordinates[:, 0] = unwrap_angles(fit.coordinates[:, 0], inl)
    if jt in (JointType.REVOLUTE, JointType.CYLINDRICAL, JointType.PLANAR,
              JointType.PRISMATIC) and inl.any():
        c = fit.coordinates[:, 0]
        fit.coordinate_range = (float(c[inl].min()), float(c[inl].max()))
        fit.motion_range = (float(c.min()), float(c.max()))
        span = fit.motion_range[1] - fit.motion_range[0]
        fit.coverage = (1.0 if span <= 0.0 else
                        (fit.coordinate_range[1] - fit.coordinate_range[0]) / span)
    n, n_out = inl.size, int((~inl).sum())
    fit.warnings = []
    if n_out > MAX_REJECTED_FRACTION * n:
        fit.warnings.append(f'{n_out} of {n} frames rejected (more than a third): the estimate '
                            f'rests on {n - n_out} frames')
    if np.isfinite(fit.coverage) and fit.coverage < MIN_COVERAGE:
        unit, f = (('mm', 1000.0) if jt == JointType.PRISMATIC else ('deg', np.rad2deg(1.0)))
        fit.warnings.append(
            f'inliers cover only {fit.coverage * 100:.0f} % of the motion '
            f'({(fit.coordinate_range[1] - fit.coordinate_range[0]) * f:.1f} of '
            f'{(fit.motion_range[1] - fit.motion_range[0]) * f:.1f} {unit})')
    if fit.degenerate:
        fit.warnings.append(fit.status or 'degenerate motion')
    if uncertainty and inl.sum() >= 2:
        u = axis_uncertainty(fit.model, R[inl], p[inl], fit.sigma_position, fit.sigma_rotation,
                             fit.point_in_b,
                             ray_ratio=fit.extra.get('line_of_sight_noise_ratio', 1.0))
        if u is not None:
            fit.axis_angle_std_in_a = u['axis_angle_std_in_a']
            fit.axis_angle_std_in_b = u['axis_angle_std_in_b']
            fit.axis_point_std = u['axis_point_std']
            fit.extra['parameter_covariance'] = u['covariance']


def estimate_joint(poses: np.ndarray, joint_type: Optional[int] = None,
                   sigma_position: Optional[float] = None,
                   sigma_rotation: Optional[float] = None,
                   robust: bool = True, refine: bool = True, correction: str = 'ml',
                   min_rotation_range: float = DEFAULT_MIN_ROTATION_RANGE,
                   min_translation_range: float = DEFAULT_MIN_TRANSLATION_RANGE,
                   stamps_ns=None, candidates: Iterable[int] = ALL_TYPES,
                   threshold: float = DEFAULT_THRESHOLD,
                   rng: Optional[np.random.Generator] = None,
                   flip_repair: bool = True, marker_normal_axis: int = 2,
                   pose_candidates: Optional[np.ndarray] = None,
                   camera_noise: bool = True, marker_weights: bool = True,
                   marker_side: Optional[float] = None) -> JointEstimation:
    """
    Estimate the joint between two links from the relative track of A in B.

    :param poses: (N, 4, 4) relative poses ``^B T_A(t)`` [m].
    :param joint_type: a :class:`JointType` to fit only that type, or None (or 255) to select
        among ``candidates`` by BIC.
    :param sigma_position: position noise std [m] per axis; None (default): estimated from the
        data, per joint type (:mod:`joint_estimator.robust`).
    :param sigma_rotation: orientation noise std [rad] per axis; None (default): estimated.
    :param robust: reject outlier frames and repair flipped poses (MSAC + refit) when True.
    :param refine: refine revolute and cylindrical joints by maximum likelihood over orientations
        and positions (:mod:`joint_estimator.refine`); False gives the chapter's estimate exactly.
    :param correction: ``'ml'`` (default; frames projected on the joint by weighted least
        squares) or ``'chapter'`` (revolute: minimal-rotation correction of Section 4).
    :param min_rotation_range: [rad], :param min_translation_range: [m] below which an axis or a
        sliding direction is reported as undefined (degenerate motion).
    :param stamps_ns: optional (N,) stamps [ns], must increase strictly.
    :param flip_repair: treat link B as a camera and link A as a square marker seen by it: each
        pose's ambiguous twin (:func:`joint_estimator.ambiguity.marker_twins`) is a candidate,
        used where it fits the joint better (robust mode only). A twin that does not fit is
        never used, so other pose sources are not harmed (at some cost in time).
    :param marker_normal_axis: the marker normal's axis in A (0 x, 1 y, 2 z).
    :param pose_candidates: (N, K, 4, 4) explicit candidate poses per frame (index 0 must be
        ``poses``), e.g. :func:`joint_estimator.ambiguity.two_link_candidates`; overrides
        ``flip_repair``.
    :param camera_noise: with estimated noise (robust mode), measure how much noisier the
        positions are along the line of sight from B's origin than across it (a camera's depth
        noise; :func:`joint_estimator.robust.line_of_sight_ratio`, from the track's second
        differences when they are noise-dominated, else 1) and whiten the position residuals
        of every type with it; ``sigma_position`` is then the noise across the line of sight.
    :param marker_weights: when the selected joint is revolute and the track is a marker seen
        by a camera (``flip_repair`` and ``camera_noise`` on, noise estimated, positions at
        least :data:`joint_estimator.marker_noise.MIN_RAY_RATIO` times noisier along the line
        of sight), refit it by maximum likelihood with each frame's own marker-pose
        information (:func:`joint_estimator.marker_noise.refine_revolute_marker`: depth and
        tilt noise per frame from the corners' geometry); the axis uncertainty is then that
        fit's. ``extra['marker_side']`` and ``extra['corner_noise_normalised']`` report the
        side used and the corner noise (pixels / focal length) estimated.
    :param marker_side: the marker's side [m] if known (also turns the weighting on when the
        line-of-sight ratio could not be measured); None: estimated from the track's
        line-of-sight noise ratio (:func:`joint_estimator.marker_noise.estimate_marker_side`).
    :raises ValueError: bad input (shape, too few poses, NaN, non-orthonormal rotation,
        stamps, non-positive sigma), or no candidate type could be fitted (the message lists
        why).
    """
    for name, v in (('sigma_position', sigma_position), ('sigma_rotation', sigma_rotation),
                    ('marker_side', marker_side)):
        if v is not None and not (np.isfinite(v) and v > 0):
            raise ValueError(f'{name} must be positive and finite (or None to estimate it), '
                             f'got {v}')
    if joint_type is not None and int(joint_type) != 255:
        types = [JointType(int(joint_type))]
    else:
        types = [JointType(int(t)) for t in candidates]
    # a joint needs motion: at least two poses, and the smallest set of the types asked for
    need = max(2, min(MIN_SAMPLES[t] for t in types))
    T = validate_track(poses, stamps_ns, min_poses=need)
    R, p = split_track(T)
    if pose_candidates is not None:
        C = np.asarray(pose_candidates, dtype=float)
        if C.ndim != 4 or C.shape[0] != T.shape[0] or C.shape[2:] != (4, 4):
            raise ValueError(f'pose_candidates: expected shape ({T.shape[0]}, K, 4, 4), got '
                             f'{C.shape}')
        validate_track(C.reshape(-1, 4, 4), name='pose candidates')
    elif flip_repair and robust:
        C = relative_candidates(T, marker_normal_axis)
    else:
        C = T[:, None]
    Rc, pc = C[:, :, :3, :3], C[:, :, :3, 3]
    rng = np.random.default_rng(0) if rng is None else rng
    result = JointEstimation(best=None)
    rows = np.arange(T.shape[0])
    chosen = {}
    # a camera's positions are noisier along the line of sight (depth) than across it;
    # measured once from the track itself and shared by every type, so that a type cannot win
    # by absorbing depth noise
    ray_ratio = (line_of_sight_ratio(p) if robust and camera_noise and sigma_position is None
                 else 1.0)
    # a spherical joint's three rotational coordinates can absorb the orientation residual
    # entirely, so it cannot estimate the orientation noise itself: it takes the median of
    # the other types' estimates (fitted first)
    order = sorted(types, key=lambda jt: jt == JointType.SPHERICAL)
    for t in order:
        sr_t = sigma_rotation
        if t == JointType.SPHERICAL and sigma_rotation is None and robust:
            others = [f.sigma_rotation for f in result.candidates.values()]
            sr_t = float(np.median(others)) if others else None
        try:
            if robust:
                rf = robust_fit(t, Rc, pc, sigma_position, sr_t, min_rotation_range,
                                min_translation_range, threshold, refine=refine, rng=rng,
                                ray_ratio=ray_ratio)
                model, inliers, choice = rf.model, rf.inliers, rf.choice
                sp, sr, estimated = rf.sigma_position, rf.sigma_rotation, rf.scale_estimated
            else:
                model = fit_model(t, R, p, min_rotation_range, min_translation_range)
                sp, sr, estimated = _plain_scales(model, R, p, sigma_position, sigma_rotation)
                if refine:
                    model = refine_model(model, R, p, sp, sr)
                    sp, sr, estimated = _plain_scales(model, R, p, sigma_position,
                                                      sigma_rotation)
                inliers, choice = None, np.zeros(T.shape[0], dtype=int)
        except (DegenerateMotionError, ValueError) as e:
            result.failures[t] = str(e)
            continue

        def scored(model, inliers, choice, sp, sr, estimated):
            R_sel, p_sel = Rc[rows, choice], pc[rows, choice]
            fit = make_fit(model, R_sel, p_sel, sp, sr, correction, inliers, ray_ratio)
            fit.repaired = (choice != 0) & fit.inliers      # twins used by inlier frames
            fit.scale_estimated = estimated or (t == JointType.SPHERICAL
                                                and sigma_rotation is None)
            fit.extra['line_of_sight_noise_ratio'] = ray_ratio
            fit.score = bic_score(fit, max(threshold, outlier_cost(sp, sr)))
            return fit, (R_sel, p_sel)

        fit, chosen[t] = scored(model, inliers, choice, sp, sr, estimated)
        if robust and Rc.shape[1] > 1 and fit.repaired[fit.inliers].mean() > 0.5:
            # most inliers replaced by a twin: a detector returns the better-fitting solution
            # more often than not, so check the hypothesis of (almost) no flips, fitted to the
            # measured poses alone, and keep the one with the lower BIC
            try:
                rf0 = robust_fit(t, Rc[:, :1], pc[:, :1], sigma_position, sr_t,
                                 min_rotation_range, min_translation_range, threshold,
                                 refine=refine, rng=rng, ray_ratio=ray_ratio)
                fit0, sel0 = scored(rf0.model, rf0.inliers, rf0.choice, rf0.sigma_position,
                                    rf0.sigma_rotation, rf0.scale_estimated)
                if fit0.score < fit.score:
                    fit, chosen[t] = fit0, sel0
            except (DegenerateMotionError, ValueError):
                pass
        result.candidates[t] = fit
    result.candidates = {t: result.candidates[t] for t in types if t in result.candidates}
    result.failures = {t: result.failures[t] for t in types if t in result.failures}
    if not result.candidates:
        raise DegenerateMotionError('no joint type could be fitted: ' + '; '.join(
            f'{t.name.lower()}: {m}' for t, m in result.failures.items()))
    result.best = min(result.candidates.values(), key=lambda f: f.score)
    marker = None
    b = result.best
    if (marker_weights and robust and camera_noise and flip_repair
            and sigma_position is None and b.joint_type == JointType.REVOLUTE
            and (ray_ratio >= MIN_RAY_RATIO or marker_side is not None)):
        marker = _marker_refit(b, Rc, pc, ray_ratio, marker_side, marker_normal_axis,
                               correction)
        if marker is not None:
            result.candidates[b.joint_type] = result.best = marker[0]
            chosen[b.joint_type] = marker[2]
    for t, fit in result.candidates.items():
        qualify_fit(fit, *chosen[t], uncertainty=fit is result.best and marker is None)
    if marker is not None:
        for key in ('axis_angle_std_in_a', 'axis_angle_std_in_b', 'axis_point_std'):
            setattr(result.best, key, marker[1][key])
        result.best.extra['parameter_covariance'] = marker[1]['covariance']
    return result


def _marker_refit(fit: JointFit, Rc: np.ndarray, pc: np.ndarray, ray_ratio: float,
                  side: Optional[float], normal_axis: int, correction: str):
    """
    Refit the revolute ``fit`` in the image space of the marker's corners.

    The measured poses are turned back into their marker corners and the joint is fitted by
    maximum likelihood on them (:func:`joint_estimator.marker_noise.refine_revolute_corners`;
    the marker side estimated from the line-of-sight ratio unless given). The robust fit's
    inliers start it; then every frame is re-classified by its corner residual (chi-square
    with 5 dof at :data:`CORNER_FRAME_QUANTILE`, the corner noise estimated from the inliers)
    and the fit repeated until the inlier set is stable: a flipped pose reprojects nearly like
    the correct one and a face-on frame's uncertain tilt is no outlier there, so the frames the
    pose-space fit had to reject or repair are used as they were measured.

    The refit is used only when the corner model explains the robust fit's inlier frames
    better (lower -2 log-likelihood of the poses, per-frame Gaussian ``sigma_n^2 W^-1``) than
    the isotropic model with the line-of-sight ratio, so a track that merely looks
    anisotropic (a noisy ratio from few frames) keeps its fit.

    :param Rc: (N, K, 3, 3), :param pc: (N, K, 3) [m]: candidate poses per frame (index 0 the
        measured pose).
    :returns: ``(new JointFit, refinement result, (R, p))`` or None when the positions are not
        in front of the camera or the refit fails or is not better.
    """
    n = Rc.shape[0]
    R, p = Rc[:, 0], pc[:, 0]
    inl = fit.inliers.copy()
    if inl.sum() < 3 or np.any(p[:, 2] <= 0.0):
        return None
    rows = np.arange(n)
    choice = np.zeros(n, dtype=int)
    if fit.repaired is not None and Rc.shape[1] > 1:
        choice[fit.repaired] = 1
    R_sel, p_sel = Rc[rows, choice], pc[rows, choice]
    estimated = side is None
    if estimated:
        side = estimate_marker_side(R_sel[inl], p_sel[inl], ray_ratio, normal_axis)
    q_all = fit.coordinates[:, 0].copy()
    threshold = float(chi2_dist.ppf(CORNER_FRAME_QUANTILE, 5))
    try:
        res = refine_revolute_corners(fit.model, R[inl], p[inl], side, normal_axis,
                                      q0=q_all[inl])
        # keep the corner model only where it explains the inliers better than the isotropic
        # one with its line-of-sight ratio (both at their own estimates, -2 log L)
        ratio = fit.extra.get('line_of_sight_noise_ratio', ray_ratio)
        iso = float(fit.chi2[inl].sum() + inl.sum() * (
            6.0 * np.log(2.0 * np.pi * fit.sigma_position * fit.sigma_rotation)
            + 2.0 * np.log(ratio)))
        first_neg2ll = res['neg2_log_likelihood']
        if not first_neg2ll < iso:
            return None
        C = marker_corners(side, normal_axis)
        uv = project_marker_corners(R, p, C)
        for _ in range(CORNER_ROUNDS):
            m = res['model']
            q_all[inl] = res['angles']
            q_all = corner_angles(m, uv, C, q_all)
            T = m.pose_at(q_all)
            r2 = np.sum((project_marker_corners(T[:, :3, :3], T[:, :3, 3], C) - uv) ** 2,
                        axis=(1, 2))
            new = r2 / res['sigma_n'] ** 2 < threshold
            if new.sum() < 3 or np.array_equal(new, inl):
                break
            inl = new
            res = refine_revolute_corners(m, R[inl], p[inl], side, normal_axis,
                                          q0=q_all[inl])
    except (np.linalg.LinAlgError, ValueError):
        return None
    m = res['model']
    if not np.all(np.isfinite(np.concatenate([m.axis_in_a, m.axis_in_b, m.point_in_a,
                                              m.point_in_b]))):
        return None
    # the fit used the measured poses; for the report and the corrected track, a frame whose
    # ambiguity twin is nearer the joint's orientation at its angle counts as flipped
    q_all[inl] = res['angles']
    q_all = corner_angles(m, uv, C, q_all)
    T = m.pose_at(q_all)
    gap = 3.0 - np.einsum('nij,nkij->nk', T[:, :3, :3], Rc)        # chordal, per candidate
    choice = np.argmin(gap, axis=1)
    R_sel, p_sel = Rc[rows, choice], pc[rows, choice]
    new = make_fit(m, R_sel, p_sel, fit.sigma_position, fit.sigma_rotation, correction, inl,
                   ray_ratio)
    new.coordinates = q_all[:, None]
    new.corrected = T
    new.rotation_residuals, new.position_residuals, _ = frame_residuals(
        R_sel, p_sel, T[:, :3, :3], T[:, :3, 3], fit.sigma_position, fit.sigma_rotation)
    new.repaired = (choice != 0) & inl
    new.scale_estimated, new.score = fit.scale_estimated, fit.score
    new.extra.update({k: v for k, v in fit.extra.items() if k not in new.extra})
    new.extra.update({'marker_side': float(side), 'marker_side_estimated': estimated,
                      'corner_noise_normalised': res['sigma_n'],
                      'isotropic_model': fit.model,
                      'isotropic_inliers': fit.inliers,
                      'isotropic_repaired': fit.repaired,
                      'neg2_log_likelihood': {'marker': first_neg2ll, 'isotropic': iso}})
    return new, res, (R_sel, p_sel)


def _plain_scales(model, R, p, sigma_position, sigma_rotation) -> tuple:
    """Noise scales of a non-robust fit: the given ones, or the RMS residual of all frames."""
    if sigma_position is not None and sigma_rotation is not None:
        return sigma_position, sigma_rotation, False
    sp0 = _START_SIGMAS[0] if sigma_position is None else sigma_position
    sr0 = _START_SIGMAS[1] if sigma_rotation is None else sigma_rotation
    rot, pos = candidate_residuals(model, R[:, None], p[:, None], sp0, sr0)
    sp, sr = rms_scales(rot[:, 0], pos[:, 0], JOINT_DOF[model.joint_type], model.n_params)
    return (sp if sigma_position is None else sigma_position,
            sr if sigma_rotation is None else sigma_rotation, True)
