"""The compiled point-to-plane ICP: exact correspondences, Open3D's iteration, recovered motion."""

import numpy as np
from object_localizer import point_to_plane as pp
import open3d as o3d
import pytest
from scipy.spatial import cKDTree
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


def _box_surface(rng, n=4000, size=(0.08, 0.04, 0.03)):
    """Sample (n, 3) [m] points of the faces of a box at 0.5 m with their outward normals."""
    half = np.array(size) / 2
    P, N = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            q = rng.uniform(-half, half, size=(n // 6, 3))
            q[:, axis] = sign * half[axis]
            nrm = np.zeros((n // 6, 3))
            nrm[:, axis] = sign
            P.append(q)
            N.append(nrm)
    return np.vstack(P) + [0.0, 0.0, 0.5], np.vstack(N)


def test_correspondences_are_the_exact_nearest_within_reach():
    rng = np.random.default_rng(1)
    P, _ = _box_surface(rng)
    # points on the surface, near it and far from it (up to 3 x reach)
    Q = P[rng.choice(len(P), 1500)] + rng.normal(0, 0.004, (1500, 3))
    Q = np.vstack([Q, P[rng.choice(len(P), 500)] + rng.uniform(-0.05, 0.05, (500, 3))])
    reach = 0.015
    for fine_cell, cell in ((0.002, reach / 2), (0.001, reach / 4), (0.004, reach)):
        fine = pp._build_grid(P, fine_cell) + (fine_cell,)
        coarse = pp._build_grid(P, cell) + (cell,)
        idx = np.empty(len(Q), np.int64)
        far, moved = np.zeros(len(Q)), np.zeros(len(Q))
        fitness, rmse, count = pp._correspond(Q, P, fine, coarse, reach, idx, far, moved)
        d, j = cKDTree(P).query(Q, distance_upper_bound=reach)
        inside = np.isfinite(d)
        assert np.array_equal(idx >= 0, inside)
        # the same distance (ties between equidistant samples may pick either)
        np.testing.assert_allclose(np.linalg.norm(P[idx[inside]] - Q[inside], axis=1),
                                   d[inside], atol=1e-12)
        assert count == int(inside.sum())
        assert fitness == pytest.approx(inside.mean())
        assert rmse == pytest.approx(np.sqrt(np.mean(d[inside] ** 2)))
        # the distances it keeps of the points beyond reach are lower bounds
        d2 = cKDTree(P).query(Q)[0]
        assert np.all(far[~inside] <= d2[~inside] + 1e-12)
        assert np.all(far[~inside] > reach)
        # points that moved less than their margin are not searched again, and stay unmatched;
        # a point moved onto the surface is found again
        moved[:] = 0.0
        Q2 = Q.copy()
        out = np.flatnonzero(~inside)
        Q2[out[0]] = P[0]
        moved[out[0]] = far[out[0]]
        pp._correspond(Q2, P, fine, coarse, reach, idx, far, moved)
        assert idx[out[0]] >= 0 and np.all(idx[out[1:]] == -1)


def test_recovers_a_small_motion_and_matches_open3d():
    rng = np.random.default_rng(2)
    P, N = _box_surface(rng, 6000)
    visible = P[:, 2] < 0.5 + 0.01        # roughly what a camera at the origin sees
    P, N = P[visible], N[visible]
    motion = make_transform(rotation_about_axis([0.3, 1.0, 0.2], 0.03), [0.003, -0.002, 0.002])
    truth_src = P[rng.choice(len(P), 1500)]
    S = (truth_src - motion[:3, 3]) @ motion[:3, :3]       # the source, moved by motion^-1
    S += rng.normal(0, 0.0003, S.shape)
    T, iterations, fitness, rmse = pp.icp_point_to_plane(S, P, N, 0.02, 0.0045, 30)
    assert 1 <= iterations <= 30
    assert fitness > 0.99 and rmse < 0.002
    moved = S @ T[:3, :3].T + T[:3, 3]
    err = np.linalg.norm(moved - truth_src, axis=1)
    assert np.median(err) < 5e-4
    # Open3D's Tukey point-to-plane ICP (which the tracker used) ends at the same pose
    reg = o3d.pipelines.registration
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(S))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(P))
    tgt.normals = o3d.utility.Vector3dVector(N)
    res = reg.registration_icp(
        src, tgt, 0.02, np.eye(4),
        reg.TransformationEstimationPointToPlane(reg.TukeyLoss(k=0.0045)),
        reg.ICPConvergenceCriteria(1e-6, 1e-6, 30))
    ref = np.asarray(res.transformation)
    assert np.abs(ref[:3, 3] - T[:3, 3]).max() < 5e-5
    assert np.abs(ref[:3, :3] - T[:3, :3]).max() < 5e-4


def test_empty_inputs_give_the_identity():
    T, iterations, fitness, _ = pp.icp_point_to_plane(np.zeros((0, 3)), np.ones((5, 3)),
                                                      np.ones((5, 3)), 0.01, 0.001)
    assert iterations == 0 and fitness == 0.0
    np.testing.assert_array_equal(T, np.eye(4))


def _torus_front(rng, n=8000, major=0.04, minor=0.012):
    """Half of a torus (axis z, centre at 0.5 m) facing a sensor at the origin, with normals."""
    u = rng.uniform(0, 2 * np.pi, n)
    v = rng.uniform(np.pi, 2 * np.pi, n)           # the half whose normals point to -z
    ring = np.column_stack([np.cos(u), np.sin(u), np.zeros(n)])
    N = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * [0.0, 0.0, 1.0]
    P = major * ring + minor * N + [0.0, 0.0, 0.5]
    return P, N


def test_residual_step_stops_a_slide_along_a_symmetry_at_the_same_fit():
    """
    A torus' spin about its axis changes no residual: the residual-step criterion stops.

    Without it the ICP keeps turning the source about the axis (the normal matrix is nearly
    singular there, the step is noise) until the tight tolerances stop it; with it the fit is
    the same: the moved points' distance to the surface and their symmetric distance (ADD-S)
    to the true points within 20 um of the full run's.
    """
    rng = np.random.default_rng(4)
    P, N = _torus_front(rng)
    truth_src = P[rng.choice(len(P), 1000)]
    R = rotation_about_axis([0.2, 0.3, 1.0], 0.03)          # about the torus' centre
    c = np.array([0.0, 0.0, 0.5])
    motion = make_transform(R, c - R @ c + [0.002, -0.001, -0.0015])
    S = (truth_src - motion[:3, 3]) @ motion[:3, :3] + rng.normal(0, 0.0003, (1000, 3))
    results = {}
    for criterion in (0.0, 1e-6):
        T, iterations, _, _ = pp.icp_point_to_plane(S, P, N, 0.02, 0.0045, 60, 1e-12, 1e-12,
                                                    min_residual_step=criterion)
        moved = S @ T[:3, :3].T + T[:3, 3]
        rel = moved - c
        # distance of the moved points to the torus surface
        surface = np.hypot(np.hypot(rel[:, 0], rel[:, 1]) - 0.04, rel[:, 2]) - 0.012
        # the error modulo the spin: T motion^-1 must keep the centre and the axis
        D = T @ np.linalg.inv(motion)
        centre_error = np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c)
        axis_error = np.arccos(np.clip(D[2, 2], -1.0, 1.0))
        results[criterion] = (iterations, surface, centre_error, axis_error)
    it0, surface0, centre0, axis0 = results[0.0]
    it1, surface1, centre1, axis1 = results[1e-6]
    assert 1 <= it1 < it0 / 4
    assert np.sqrt(np.mean(surface1 ** 2)) < 5e-4
    assert abs(np.median(surface1) - np.median(surface0)) < 2e-5
    assert centre1 < 2e-4 and axis1 < 5e-3
    assert abs(centre1 - centre0) < 3e-5 and abs(axis1 - axis0) < 5e-4


def _sphere_front(rng, n=8000, radius=0.03):
    """Half of a sphere (centre at 0.5 m) facing a sensor at the origin, with normals."""
    N = rng.normal(size=(n, 3))
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    N[:, 2] = -np.abs(N[:, 2])
    return radius * N + [0.0, 0.0, 0.5], N


def _spin_and_error(T, motion, c, axis):
    """(turn about ``axis`` [rad], centre error [m], axis tilt [rad]) of T relative to truth."""
    from stereo_manip_tools.transforms import rotation_log
    D = T @ np.linalg.inv(motion)          # identity up to a turn about the symmetry axis
    centre_error = float(np.linalg.norm(D[:3, :3] @ c + D[:3, 3] - c))
    tilt = float(np.arccos(np.clip(axis @ D[:3, :3] @ axis, -1.0, 1.0)))
    spin = float(rotation_log(T[:3, :3]) @ axis)
    return spin, centre_error, tilt


@pytest.mark.parametrize('seed', [5, 6, 7])
def test_a_locked_symmetry_axis_gives_no_spin_and_the_true_pose(seed):
    """
    ICP on a torus with its axis locked: exactly no spin, few iterations, the true pose.

    Sampled target, other samples + 0.5 mm noise as the source, moved by a small motion (turn
    and shift, the tracker's size). Against the truth modulo the spin: centre within 0.2 mm,
    axis within 3 mrad, and no worse than the free run (which may turn about the axis); no
    more iterations than the free run. (The spin that runs the free ICP to ``max_iterations``
    needs the faceted model and a cluttered cloud: test_tracking.py.)
    """
    rng = np.random.default_rng(seed)
    P, N = _torus_front(rng)
    truth_src = _torus_front(rng, 1500)[0]
    c, axis = np.array([0.0, 0.0, 0.5]), np.array([0.0, 0.0, 1.0])
    R = rotation_about_axis([0.2, 0.3, 1.0], 0.03)
    motion = make_transform(R, c - R @ c + [0.002, -0.001, -0.0015])
    S = (truth_src - motion[:3, 3]) @ motion[:3, :3] + rng.normal(0, 0.0005, (1500, 3))
    out = {}
    for locked in (None, axis[None, :]):
        T, iterations, _, _ = pp.icp_point_to_plane(S, P, N, 0.02, 0.0045, 30,
                                                    locked_rotations=locked)
        out[locked is None] = (iterations, _spin_and_error(T, np.eye(4), c, axis)[0]) + \
            _spin_and_error(T, motion, c, axis)[1:]
    it_free, _, centre_free, tilt_free = out[True]
    it_locked, spin, centre, tilt = out[False]
    # no turn about the locked axis but the second-order one of composing the small turns
    # about the other two (Rz Ry Rx of a 0.03 rad correction: ~1e-5 rad)
    assert abs(spin) < 1e-4
    assert 1 <= it_locked <= min(it_free, 8)
    assert centre < 2e-4 and tilt < 3e-3
    assert centre <= centre_free + 5e-5 and tilt <= tilt_free + 5e-4


def test_a_sphere_with_every_rotation_locked_is_moved_by_a_translation_only():
    """Sphere: every direction locked (a pure translation) recovers the centre in few steps."""
    rng = np.random.default_rng(8)
    P, N = _sphere_front(rng)
    truth_src = _sphere_front(rng, 1500)[0]
    shift = np.array([0.003, -0.002, 0.0025])
    S = truth_src - shift + rng.normal(0, 0.0005, truth_src.shape)
    T, iterations, _, _ = pp.icp_point_to_plane(S, P, N, 0.02, 0.0045, 30,
                                                locked_rotations=np.eye(3) * 2.0)
    np.testing.assert_allclose(T[:3, :3], np.eye(3), atol=1e-12)
    assert 1 <= iterations <= 8
    assert np.linalg.norm(T[:3, 3] - shift) < 2e-4
