"""Per-frame marker-pose noise and the revolute fit weighted by it, against ground truth."""

import cv2
from joint_estimator.common import compose_track, JointType, rotation_vectors
from joint_estimator.common import minimal_rotations_onto, rotations_about_axis
from joint_estimator.evaluation import axis_angle_deg, line_distance_over_segment
from joint_estimator.marker_noise import (
    estimate_marker_side, marker_corners, marker_information, refine_revolute_corners,
    refine_revolute_marker)
from joint_estimator.revolute import RevoluteModel
from joint_estimator.robust import line_of_sight_ratio
from joint_estimator.selection import estimate_joint
from joint_estimator.synthetic import add_noise, add_outliers, random_joint_motion
import numpy as np
from scipy.spatial.transform import Rotation

F_PX = 1400.0
K = np.array([[F_PX, 0.0, 960.0], [0.0, F_PX, 540.0], [0.0, 0.0, 1.0]])


def _line_distance_mm(c_true, l_true, anchor, c, u):
    return 1000.0 * line_distance_over_segment(c_true, l_true, anchor, c, u)


def _ippe_door(seed, n=300, side=0.07, sigma_px=0.8, distance=1.2):
    """
    Simulate a door with a marker seen through OpenCV's IPPE_SQUARE solver.

    A door (hinge ~ camera y, ``distance`` ahead) with a marker seen through OpenCV's
    IPPE_SQUARE solver; returns truth, the solver's poses (``detected``) and the solution
    nearest the truth per frame (``unflipped``: the pose noise without the flips).
    """
    rng = np.random.default_rng(seed)
    axis = np.array([0.0, 1.0, 0.0])
    hinge = np.array([rng.uniform(-0.2, 0.2), 0.0, distance])
    R0 = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    t0 = hinge + np.array([0.35, 0.05, 0.0])
    q = np.deg2rad(np.linspace(-60.0, 30.0, n))
    Rq = rotations_about_axis(axis, q)
    truth = compose_track(Rq @ R0, hinge + np.einsum('nij,j->ni', Rq, t0 - hinge))
    corners = marker_corners(side)
    detected, unflipped = [], []
    for T in truth:
        img = (corners @ T[:3, :3].T + T[:3, 3]) @ K.T
        img = img[:, :2] / img[:, 2:] + rng.normal(0.0, sigma_px, (4, 2))
        _, rvecs, tvecs, _ = cv2.solvePnPGeneric(corners, img, K, None,
                                                 flags=cv2.SOLVEPNP_IPPE_SQUARE)
        sols = [compose_track(cv2.Rodrigues(r)[0][None], np.asarray(t).reshape(1, 3))[0]
                for r, t in zip(rvecs, tvecs)]
        err = [np.linalg.norm(Rotation.from_matrix(S[:3, :3] @ T[:3, :3].T).as_rotvec())
               for S in sols]
        detected.append(sols[0])
        unflipped.append(sols[int(np.argmin(err))])
    return {'truth': truth, 'detected': np.array(detected), 'unflipped': np.array(unflipped),
            'axis_b': axis, 'point_b': hinge, 'axis_a': R0.T @ axis,
            'point_a': R0.T @ (hinge - t0), 'side': side, 'sigma_n': sigma_px / F_PX}


def _errors(track, axis_a, axis_b, point_a, point_b, poses):
    anchor_b = poses[:, :3, 3].mean(axis=0)
    ang = max(axis_angle_deg(axis_a, track['axis_a']), axis_angle_deg(axis_b, track['axis_b']))
    line = max(_line_distance_mm(track['point_b'], track['axis_b'], anchor_b, point_b, axis_b),
               _line_distance_mm(track['point_a'], track['axis_a'], np.zeros(3), point_a,
                                 axis_a))
    return ang, line


def test_information_is_the_corner_jacobian_and_predicts_the_solver_noise():
    tr = _ippe_door(0)
    T = tr['truth']
    W = marker_information(T[:, :3, :3], T[:, :3, 3], tr['side'])
    # numerical Jacobian of the normalised corner projections for one frame
    corners = marker_corners(tr['side'])

    def project(x, Tk):
        R = Rotation.from_rotvec(x[:3]).as_matrix() @ Tk[:3, :3]
        X = corners @ R.T + Tk[:3, 3] + x[3:]
        return (X[:, :2] / X[:, 2:]).ravel()

    k = 40
    J = np.empty((8, 6))
    for j in range(6):
        e = np.zeros(6)
        e[j] = 1e-7
        J[:, j] = (project(e, T[k]) - project(-e, T[k])) / 2e-7
    np.testing.assert_allclose(W[k], J.T @ J, rtol=1e-5, atol=1e-6 * np.abs(W[k]).max())
    # the solver's pose errors (flips undone) follow sigma_n^2 W^-1: chi-square with 6 dof
    U = tr['unflipped']
    r = np.concatenate([rotation_vectors(U[:, :3, :3] @ np.transpose(T[:, :3, :3], (0, 2, 1))),
                        U[:, :3, 3] - T[:, :3, 3]], axis=1)
    chi2 = np.einsum('ni,nij,nj->n', r, W, r) / tr['sigma_n'] ** 2
    assert 0.8 < chi2.mean() / 6.0 < 1.25, chi2.mean()
    # and depth is far noisier than the lateral position
    cov = np.linalg.inv(W)[:, 3:, 3:]
    v = T[:, :3, 3] / np.linalg.norm(T[:, :3, 3], axis=1)[:, None]
    along = np.einsum('ni,nij,nj->n', v, cov, v)
    across = (np.trace(cov, axis1=1, axis2=2) - along) / 2.0
    assert np.median(np.sqrt(along / across)) > 10.0


def test_marker_side_estimated_from_the_line_of_sight_ratio():
    for side in (0.05, 0.1):
        tr = _ippe_door(1, side=side)
        p = tr['unflipped'][:, :3, 3]
        est = estimate_marker_side(tr['unflipped'][:, :3, :3], p, line_of_sight_ratio(p))
        assert side / 1.6 < est < side * 1.6, (side, est)


def test_weighted_fit_beats_the_isotropic_one_and_reports_its_uncertainty():
    iso, wml, z = [], [], []
    for seed in range(4):
        tr = _ippe_door(10 + seed)
        U = tr['unflipped']
        est = estimate_joint(U, joint_type=JointType.REVOLUTE)
        b = est.best
        assert 'marker_side' in b.extra              # the per-frame model was used
        m0 = b.extra['isotropic_model']
        inl = b.inliers
        s0 = float((U[inl, :3, 3].mean(axis=0) - m0.point_in_b) @ m0.axis_in_b)
        iso.append(_errors(tr, m0.axis_in_a, m0.axis_in_b, m0.point_in_a + s0 * m0.axis_in_a,
                           m0.point_in_b + s0 * m0.axis_in_b, U)[1])
        ang, line = _errors(tr, b.axis_in_a, b.axis_in_b, b.point_in_a, b.point_in_b, U)
        assert ang < 0.5, ang
        wml.append(line)
        z.append(line / 1000.0 / b.axis_point_std)
        # the estimated corner noise is the generator's (in normalised image units)
        assert 0.7 < b.extra['corner_noise_normalised'] / tr['sigma_n'] < 1.3
    assert np.mean(wml) < 0.7 * np.mean(iso), (wml, iso)
    assert max(wml) < 8.0, wml
    # the reported axis-point std is calibrated: the line distance (max over A, B and +-0.1 m,
    # so a little above the centre's error) over the std has a median near 1 (0.96 at the
    # centre, 1.12 for this distance on 8 bench tracks); a std 3x too small (the forward-
    # difference Jacobian before) or 3x too large fails
    assert 0.33 < np.median(z) < 3.0, z


def _corner_bound_point_std(tr):
    """Cramer-Rao std [m] of the axis point in B (data centre) from the corners, true joint."""
    a, b = tr['axis_a'], tr['axis_b']
    m = RevoluteModel(a, b, tr['point_a'], tr['point_b'], minimal_rotations_onto(a[None], b)[0],
                      1.0)
    T = tr['truth']
    res = refine_revolute_corners(m, T[:, :3, :3], T[:, :3, 3], tr['side'], rounds=0)
    return res['axis_point_std'] * tr['sigma_n'] / res['sigma_n']


def test_flipped_marker_tracks_reach_the_corner_bound_without_rejecting_frames():
    """
    Check the default estimate on solver poses (flips included) against the Cramer-Rao bound.

    The doors' poses come from OpenCV's IPPE_SQUARE on noisy corners, with no outlier frame:
    their errors are non-Gaussian (a face-on marker's tilt, the flips). The default estimate
    (sigmas, side unknown) is fitted in the corners' image space, where they are ordinary
    noise: at most 2 % of the frames may be rejected (the pose-space fit rejected 10-16 % of
    these tracks' frames, 29-48 of 300) and the axis point's error in B at the data's centre
    must be near the bound from the corners' Jacobian at the true joint: for an efficient
    estimator the mean of (error / bound std)^2 over 8 tracks is chi-square(16) / 16, below
    2.45 (RMS ratio 1.57) with probability 0.999. Measured: 1.47 (0-2 frames rejected); the
    previous pose-space fit (main at eeff1ae): 2.09, 29-48 frames rejected per track.
    """
    ratios = []
    for seed in range(30, 38):
        tr = _ippe_door(seed)
        D = tr['detected']
        b = estimate_joint(D).best
        assert b.joint_type == JointType.REVOLUTE
        assert 'corner_noise_normalised' in b.extra          # the corner refit was used
        assert b.outlier_indices.size <= 0.02 * D.shape[0], (seed, b.outlier_indices.size)
        ang, _ = _errors(tr, b.axis_in_a, b.axis_in_b, b.point_in_a, b.point_in_b, D)
        assert ang < 0.5, (seed, ang)
        err = line_distance_over_segment(tr['point_b'], tr['axis_b'], D[:, :3, 3].mean(axis=0),
                                         b.point_in_b, b.axis_in_b, half_length=0.0)
        ratios.append(err / _corner_bound_point_std(tr))
    assert np.sqrt(np.mean(np.square(ratios))) < 1.57, ratios


def test_known_side_and_the_flipped_track():
    tr = _ippe_door(20)
    est = estimate_joint(tr['detected'], marker_side=tr['side'])
    b = est.best
    assert b.joint_type == JointType.REVOLUTE
    assert b.extra['marker_side'] == tr['side'] and not b.extra['marker_side_estimated']
    ang, line = _errors(tr, b.axis_in_a, b.axis_in_b, b.point_in_a, b.point_in_b,
                        tr['detected'])
    assert ang < 1.0 and line < 5.0, (ang, line)
    # the refit alone, from the truth, stays near the truth
    T = tr['truth']
    res = refine_revolute_marker(b.model, tr['unflipped'][:, :3, :3],
                                 tr['unflipped'][:, :3, 3], tr['side'])
    m = res['model']
    assert axis_angle_deg(m.axis_in_b, tr['axis_b']) < 0.5
    assert res['information'].shape == (T.shape[0], 6, 6)


def test_generic_tracks_keep_the_isotropic_model():
    rng = np.random.default_rng(3)
    g = random_joint_motion(JointType.REVOLUTE, 100, rng, rotation_range=np.deg2rad(90.0))
    est = estimate_joint(add_noise(g.poses, 0.001, np.deg2rad(1.0), rng))
    assert est.best.joint_type == JointType.REVOLUTE
    assert 'marker_side' not in est.best.extra


def test_small_track_with_outliers_is_not_taken_over_by_twins():
    """
    Check that a small track with outliers is not taken over by twins.

    N = 20, 30 deg, 20 % outliers (the accuracy bench's hardest cell, its seeds): a few
    seeds used to fit twins of most frames (78 deg off) or the per-frame marker model on a
    generic track (35 deg off). Of its 50 seeds, with the two guards in ``selection`` removed
    (the no-flip hypothesis when most inliers are twins; the marker refit only with the lower
    -2 log L) seed 43 comes out 78 deg off and seed 1 38 deg off (the next worst 3.9 deg): the
    test runs those two and six others (the worst of the rest among them) to stay fast.
    """
    sp, sr, n = 0.001, np.deg2rad(1.0), 20
    worst, rot_fit, rot_raw = 0.0, [], []
    for seed in (43, 1, 11, 4, 15, 0, 2, 3):
        rng = np.random.default_rng([seed, n, 2, 0, int(sp * 1e4), int(sr * 1e4)])
        g = random_joint_motion(JointType.REVOLUTE, n, rng, rotation_range=np.deg2rad(30.0))
        noisy, out = add_outliers(add_noise(g.poses, sp, sr, rng), 0.2, rng)
        b = estimate_joint(noisy, joint_type=JointType.REVOLUTE, rng=rng).best
        worst = max(worst, axis_angle_deg(b.axis_in_a, g.axis_in_a),
                    axis_angle_deg(b.axis_in_b, g.axis_in_b))
        Gt = g.poses[~out, :3, :3]
        for Rx, acc in ((b.corrected[~out, :3, :3], rot_fit), (noisy[~out, :3, :3], rot_raw)):
            acc.append(np.linalg.norm(rotation_vectors(Rx @ np.transpose(Gt, (0, 2, 1))),
                                      axis=1).mean())
    assert worst < 8.0, worst
    assert np.mean(rot_fit) < np.mean(rot_raw)


def test_marker_side_must_be_positive():
    tr = _ippe_door(2, n=30)
    for bad in (0.0, -0.05, float('nan')):
        try:
            estimate_joint(tr['detected'], marker_side=bad)
        except ValueError as exc:
            assert 'marker_side' in str(exc)
        else:
            raise AssertionError(f'marker_side={bad} accepted')
