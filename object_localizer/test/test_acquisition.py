"""
Global acquisition against ground truth.

PPF voting, visibility verification, symmetry-aware errors, and acquire_object on a stereo cloud of
a synthetic scene (pure core, no ROS).
"""

from dataclasses import replace

import numpy as np
from object_localizer.acquisition import (acquire_object, prepare_acquisition_model,
                                          prepare_acquisition_scene)
from object_localizer.evaluation import sample_visible_surface
from object_localizer.ppf import cluster_poses, ppf_vote
from object_localizer.symmetry import find_symmetries, symmetric_pose_error
from object_localizer.verification import (observe_depth, PinholeCamera, sample_model_surface,
                                           score_pose_visibility, unoccluded_mask)
import pytest
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.transforms import make_transform, rotation_about_axis

CAMERA = PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480)


@pytest.fixture(scope='module')
def meshes():
    return {n: load_obj(find_model(n)) for n in ('peg', 'hole_block', 'cube', 'cylinder',
                                                 'sphere', 'link_arm')}


@pytest.fixture(scope='module')
def symmetries(meshes):
    out = {}
    for name, mesh in meshes.items():
        s = sample_model_surface(mesh, 0.003, max_samples=8000)
        out[name] = find_symmetries(s.points, s.spacing)
    return out


def test_symmetry_groups_of_the_shipped_models(symmetries):
    assert len(symmetries['cube'].rotations) == 24          # the rotation group of a cube
    assert len(symmetries['peg'].rotations) == 8            # square prism: D4
    assert len(symmetries['hole_block'].rotations) == 8
    assert len(symmetries['link_arm'].rotations) == 4       # brick with three unequal edges
    assert symmetries['sphere'].fully_symmetric
    axes = symmetries['cylinder'].continuous_axes
    assert len(axes) == 1 and abs(abs(axes[0][2]) - 1.0) < 1e-6


def test_symmetric_pose_error_ignores_symmetries_and_sees_real_errors(symmetries):
    T = make_transform(rotation_about_axis([0.3, -0.2, 1.0], 0.7), [0.02, -0.01, 0.5])
    sym = symmetries['peg']
    c = sym.centroid
    for R in sym.rotations:
        # the truth composed with a symmetry about the centroid: an equivalent pose
        S = make_transform(R, c - R @ c)
        e_t, e_r = symmetric_pose_error(T @ S, T, sym)
        assert e_t < 1e-9 and e_r < 1e-6
    off = T @ make_transform(rotation_about_axis([1.0, 0.0, 0.0], np.radians(5.0)), np.zeros(3))
    e_t, e_r = symmetric_pose_error(off, T, sym)
    assert np.degrees(e_r) == pytest.approx(5.0, abs=0.01)
    # a cylinder turned about its own axis is the same pose; tilted it is not
    cyl = symmetries['cylinder']
    spun = T @ make_transform(rotation_about_axis(cyl.continuous_axes[0], 1.0), np.zeros(3))
    assert symmetric_pose_error(spun, T, cyl)[1] < np.radians(0.2)
    tilted = T @ make_transform(rotation_about_axis([1.0, 0.0, 0.0], 0.1), np.zeros(3))
    assert symmetric_pose_error(tilted, T, cyl)[1] == pytest.approx(0.1, abs=0.005)


def _scene_of(meshes, name, T, rng, noise=0.0005):
    P = sample_visible_surface(meshes[name], T, 30000, seed=int(rng.integers(1 << 30)))
    table = np.stack([rng.uniform(-0.25, 0.25, 20000), rng.uniform(-0.2, 0.2, 20000),
                      np.full(20000, 0.75)], axis=1)
    return np.vstack([P, table]) + rng.normal(scale=noise, size=(len(P) + len(table), 3))


def test_visibility_score_prefers_the_true_pose_and_sees_free_space_violations(meshes):
    rng = np.random.default_rng(0)
    T = make_transform(rotation_about_axis([1.0, 0.2, 0.1], 2.2), [0.01, 0.02, 0.55])
    cloud = _scene_of(meshes, 'hole_block', T, rng)
    observed = observe_depth(cloud, CAMERA)
    surface = sample_model_surface(meshes['hole_block'])
    truth = score_pose_visibility(surface, T, observed)
    assert truth.score > 0.8 and truth.violation_fraction < 0.05
    # 3 cm closer to the camera: the surface floats in front of what is seen (no violations,
    # nothing inlier); 3 cm further: the camera sees the object where the model claims free
    # space in front of it -> occlusions; shifted sideways: violations on the uncovered side
    closer = T.copy()
    closer[:3, 3] *= 0.95
    sideways = T.copy()
    sideways[:3, 3] += [0.04, 0.0, 0.0]
    for pose in (closer, sideways):
        s = score_pose_visibility(surface, pose, observed)
        assert s.score < 0.5 * truth.score, s
    s = score_pose_visibility(surface, sideways, observed)
    assert s.violation_fraction > 0.15, s
    # the same without intrinsics: a virtual camera gives the same ranking
    virtual = observe_depth(cloud)
    assert score_pose_visibility(surface, T, virtual).score > \
        2.0 * score_pose_visibility(surface, sideways, virtual).score


def test_unoccluded_mask_drops_points_hidden_behind_an_occluder():
    P = np.array([[0.0, 0.0, 0.5], [0.05, 0.0, 0.5]])
    N = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    wall = np.stack([np.linspace(-0.01, 0.01, 50), np.zeros(50), np.full(50, 0.4)], axis=1)
    far = np.array([[0.05, 0.0, 0.5]])
    observed = observe_depth(np.vstack([wall, far]), CAMERA, stride=1)
    mask = unoccluded_mask(P, N, observed, 0.005)
    assert mask.tolist() == [False, True]


def test_ppf_voting_finds_the_pose_in_a_clean_cloud(meshes, symmetries):
    rng = np.random.default_rng(3)
    model = prepare_acquisition_model(meshes['peg'])
    T = make_transform(rotation_about_axis([0.2, 1.0, -0.4], 1.9), [-0.03, 0.01, 0.6])
    scene = prepare_acquisition_scene(_scene_of(meshes, 'peg', T, rng))
    pcd = scene.cloud(model.ppf.distance_step, drop_plane=True,
                      min_plane_extent=2 * model.diameter)
    poses, votes = ppf_vote(model.ppf, np.asarray(pcd.points), np.asarray(pcd.normals),
                            reference_stride=2)
    poses, scores = cluster_poses(poses, votes, model.centroid, 0.1 * model.diameter,
                                  np.radians(20.0))
    errors = [symmetric_pose_error(P, T, symmetries['peg']) for P in poses[:5]]
    # a rough pose: within the PPF sampling step and a few angle bins of the truth
    assert min(e_t for e_t, e_r in errors if e_r < np.radians(15)) < model.ppf.distance_step


@pytest.mark.parametrize('method', ['ppf', 'fpfh'])
def test_acquire_object_on_sampled_scene(meshes, symmetries, method):
    rng = np.random.default_rng(5)
    model = prepare_acquisition_model(meshes['link_arm'])
    T = make_transform(rotation_about_axis([0.5, -0.3, 1.0], 2.6), [0.04, -0.02, 0.55])
    hyps = acquire_object(model, _scene_of(meshes, 'link_arm', T, rng), camera=CAMERA,
                          method=method, seed=1, time_budget_s=30.0)
    assert hyps and hyps[0].refined and hyps[0].method == method
    e_t, e_r = symmetric_pose_error(hyps[0].pose, T, symmetries['link_arm'])
    assert e_t < 0.002 and e_r < np.radians(2.0), (e_t, np.degrees(e_r))
    assert hyps[0].score > 0.5
    # the best first (a near-tie's runner-up when the check supports it more), then by score
    rest = [h for h in hyps[1:] if h.refined]
    assert all(a.score >= b.score for a, b in zip(rest, rest[1:]))


def _arm_scene_with_spied_preparation(meshes, monkeypatch):
    """Return link_arm's pose, a cloud of it and the list every scene preparation joins."""
    from object_localizer import acquisition
    rng = np.random.default_rng(5)
    T = make_transform(rotation_about_axis([0.5, -0.3, 1.0], 2.6), [0.04, -0.02, 0.55])
    cloud = _scene_of(meshes, 'link_arm', T, rng)
    prepared = []
    prepare = acquisition.prepare_acquisition_scene

    def spy(*args, **kwargs):
        prepared.append(prepare(*args, **kwargs))
        return prepared[-1]
    monkeypatch.setattr(acquisition, 'prepare_acquisition_scene', spy)
    return T, cloud, prepared


def test_tracker_acquirer_uses_the_camera_it_is_given(meshes, symmetries, monkeypatch):
    """make_acquirer scores with the camera and baseline of its callables (the node's wiring)."""
    from object_localizer.tracking import make_acquirer, prepare_tracking_model
    T, cloud, scenes = _arm_scene_with_spied_preparation(meshes, monkeypatch)
    model = prepare_tracking_model(meshes['link_arm'])
    camera = [None]
    acquire = make_acquirer('ppf', time_budget_s=30.0, camera=lambda: camera[0],
                            stereo_baseline=lambda: 0.1)
    for cam in (None, CAMERA):
        camera[0] = cam
        poses = acquire(model, cloud, 1)
        e_t, e_r = symmetric_pose_error(poses[0], T, symmetries['link_arm'])
        assert e_t < 0.002 and e_r < np.radians(2.0), (cam, e_t, np.degrees(e_r))
        observed = scenes[-1].observed()
        assert observed.camera.baseline == 0.1 and observed.right is not None
        if cam is not None:
            # the camera's pixels (coarsened by 4 or more: this cloud is unorganised), not a
            # virtual camera's
            stride = CAMERA.fx / observed.camera.fx
            assert stride >= 4.0
            assert observed.camera == replace(CAMERA.scaled(stride), baseline=0.1)


def test_tracker_acquirer_prepares_a_cloud_once_for_its_objects(meshes, symmetries, monkeypatch):
    """The trackers of one cloud (one points array, one camera) share its scene preparation."""
    from object_localizer.tracking import make_acquirer, prepare_tracking_model
    T, cloud, prepared = _arm_scene_with_spied_preparation(meshes, monkeypatch)
    arm, peg = prepare_tracking_model(meshes['link_arm']), prepare_tracking_model(meshes['peg'])
    camera = [CAMERA]
    acquire = make_acquirer('ppf', time_budget_s=30.0, camera=lambda: camera[0])
    first = acquire(arm, cloud, 1)
    acquire(peg, cloud, 1)
    assert len(prepared) == 1
    again = acquire(arm, cloud.copy(), 1)           # the next cloud: a new array
    camera[0] = replace(CAMERA, baseline=0.1)
    acquire(arm, cloud, 1)                          # the same array, another camera
    assert len(prepared) == 3
    for poses in (first, again):
        e_t, e_r = symmetric_pose_error(poses[0], T, symmetries['link_arm'])
        assert e_t < 0.002 and e_r < np.radians(2.0), (e_t, np.degrees(e_r))


def _stereo_cloud(scene_name, frame, seed, num_disparities=160, min_disparity=0):
    """
    Run a frame of a synthetic scene through block matching (the benchmarks' stereo).

    :return: the organised cloud (H, W, 3) [m, left optical frame], the camera mapping of
        the truth (intrinsics and baseline), and the truth.
    """
    from stereo_depth.pipeline import compute_disparity, disparity_to_points
    from stereo_depth.synthetic import render
    left, right, truth = render(scene_name, frame, seed=seed)
    cam = truth['camera']
    disp = compute_disparity(left, right, 'block_matching', num_disparities,
                             min_disparity=min_disparity)
    return (disparity_to_points(disp, cam['fx'], cam['fy'], cam['cx'], cam['cy'],
                                cam['baseline']), cam, truth)


@pytest.fixture(scope='module')
def stereo_frame():
    """Frame 20 of peg_in_hole through the demo's stereo settings: an organised cloud."""
    pts, cam, truth = _stereo_cloud('peg_in_hole', 20, 0)
    return pts, cam, truth['poses']


@pytest.mark.slow
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_acquire_every_object_of_a_stereo_frame(meshes, symmetries, stereo_frame, seed):
    pts, cam, poses = stereo_frame
    scene = prepare_acquisition_scene(pts, camera=cam)
    for name in ('peg', 'hole_block'):
        model = prepare_acquisition_model(meshes[name])
        hyps = acquire_object(model, scene, seed=seed, time_budget_s=30.0)
        e_t, e_r = symmetric_pose_error(hyps[0].pose, poses[name], symmetries[name])
        assert e_t < 0.002 and e_r < np.radians(2.0), (name, e_t, np.degrees(e_r))


@pytest.mark.parametrize('seed,frame,acquisition_seed', [(0, 31, 34), (1, 79, 42)])
def test_slot_block_with_its_peg_is_not_turned_onto_its_side(seed, frame, acquisition_seed):
    """
    The slot block of peg_in_slot, on stereo clouds, is found the right way up.

    Turned 90 deg onto its side the block shows its whole outline on depth edges (edges 0.96)
    while the true pose, resting on the table, shows about half (0.51); with the edge support
    weighted linearly the turned pose outranked the truth in these frames (bench trials 34 and
    42 of localizer_acquisition, same seeds). Checked: the orientation (2 deg) and the place
    (5 mm, the project's wrong-pose line); the 2 mm accuracy is the benchmark's, over 210
    trials (with two voting rounds frame 31 ends 2.3 mm off, the right way up).
    """
    pts, cam, truth = _stereo_cloud('peg_in_slot', frame, seed)
    mesh = load_obj(find_model('slot_block'))
    samples = sample_model_surface(mesh, 0.003, max_samples=8000)
    sym = find_symmetries(samples.points, samples.spacing)
    hyps = acquire_object(prepare_acquisition_model(mesh),
                          prepare_acquisition_scene(pts, camera=cam), seed=acquisition_seed,
                          time_budget_s=float('inf'))
    e_t, e_r = symmetric_pose_error(hyps[0].pose, np.asarray(truth['poses']['slot_block']), sym)
    assert e_r < np.radians(2.0) and e_t < 0.005, (e_t, np.degrees(e_r))


@pytest.mark.parametrize('scene_name,seed,frame,name,acquisition_seed', [
    ('peg_in_hole', 2, 46, 'peg', 5), ('primitives', 0, 64, 'superquadric', 159)])
def test_partly_hidden_object_outranks_a_fully_visible_wrong_pose(
        scene_name, seed, frame, name, acquisition_seed):
    """
    A right pose half hidden by a contact partner is ranked above a wrong, fully visible one.

    Stereo clouds of bench trials 5 and 159 of localizer_acquisition (same seeds). The coarse
    pixel score counts occluded pixels against a pose: the peg standing in its hole (19 % of its
    pixels hidden by the block) scored 0.56 against 0.70 for the peg lying flat on the block's
    top face 141 mm away, and the superquadric ICP stage 6 deg off scored above the pose 1 deg
    off. Ranked by the tracker's per-sample check (occluded samples not counted, normal
    distances, stereo visibility) the right poses come first.
    """
    pts, cam, truth = _stereo_cloud(scene_name, frame, seed)
    mesh = load_obj(find_model(name))
    samples = sample_model_surface(mesh, 0.003, max_samples=8000)
    sym = find_symmetries(samples.points, samples.spacing)
    hyps = acquire_object(prepare_acquisition_model(mesh),
                          prepare_acquisition_scene(pts, camera=cam), seed=acquisition_seed,
                          time_budget_s=float('inf'), final_check=True)
    assert all(a.check.quality * a.score >= b.check.quality * b.score
               for a, b in zip(hyps, hyps[1:]) if b.refined)
    e_t, e_r = symmetric_pose_error(hyps[0].pose, np.asarray(truth['poses'][name]), sym)
    assert e_t < 0.002 and e_r < np.radians(2.0), (e_t, np.degrees(e_r))


def test_stereo_aware_score_ranks_the_peg_in_its_hole_above_the_peg_lying_on_the_block(
        meshes):
    """
    The visibility score knows what stereo can measure (camera baseline given).

    Stereo cloud of bench trial 5 of localizer_acquisition (peg_in_hole, seed 2, frame 46):
    the peg stands in its hole, and its side face, seen at 69 deg incidence by the left camera
    and 80 deg by the right one, gets the block's disparity from block matching. Counted as
    free-space violations (19 % of the peg's pixels) they made the true pose score 0.56
    against 0.70 for the peg lying on the block's top face (a wrong pose 141 mm away, chosen
    on main). With the baseline the score takes those pixels as unmeasurable (unknown), so
    the truth ranks first; a real violation (a pose shifted off the peg) still counts.
    """
    pts, cam, truth = _stereo_cloud('peg_in_hole', 46, 2)
    surface = sample_model_surface(meshes['peg'])
    T = np.asarray(truth['poses']['peg'])
    # the peg lying on the block's top face (block frame), as main's acquisition returned it
    R = np.array([[-0.0328, -0.9991, -0.0251], [-0.0004, 0.0251, -0.9997],
                  [0.9995, -0.0327, -0.0012]])
    U, _, Vt = np.linalg.svd(R)
    lying = np.asarray(truth['poses']['hole_block']) @ make_transform(U @ Vt,
                                                                      [-0.0608, 0.04, -0.0198])
    assert np.linalg.norm(lying[:3, 3] - T[:3, 3]) > 0.1
    stereo = observe_depth(pts, cam)
    assert stereo.camera.baseline == pytest.approx(cam['baseline'])
    right_pose = score_pose_visibility(surface, T, stereo)
    wrong = score_pose_visibility(surface, lying, stereo)
    assert right_pose.violation_fraction < 0.05, right_pose
    assert right_pose.combined > wrong.combined + 0.03, (right_pose, wrong)
    # without the baseline (no stereo model) the side face counts against the truth
    mono = observe_depth(pts, {k: cam[k] for k in ('fx', 'fy', 'cx', 'cy', 'width', 'height')})
    assert score_pose_visibility(surface, T, mono).violation_fraction > 0.1
    assert score_pose_visibility(surface, T, mono).combined < \
        score_pose_visibility(surface, lying, mono).combined
    # the peg shifted 1 cm sideways: the table seen through it is measurable, a violation
    off = T.copy()
    off[:3, 3] += [0.0, 0.01, 0.0]
    shifted = score_pose_visibility(surface, off, stereo)
    assert shifted.violation_fraction > 0.1 and shifted.combined < 0.5 * right_pose.combined


def test_bad_input_is_refused(meshes):
    model = prepare_acquisition_model(meshes['cube'])
    with pytest.raises(ValueError, match='method'):
        acquire_object(model, np.zeros((100, 3)) + [0, 0, 1], method='sift')
    with pytest.raises(ValueError, match='finite points'):
        acquire_object(model, np.full((100, 3), np.nan))
    with pytest.raises(ValueError, match='shape'):
        prepare_acquisition_scene(np.zeros((10, 2)))


def test_localize_uses_acquisition_for_its_global_search(meshes, symmetries):
    from object_localizer.localization import localize
    rng = np.random.default_rng(8)
    model = prepare_acquisition_model(meshes['peg'])
    T = make_transform(rotation_about_axis([-0.4, 1.0, 0.3], 1.1), [0.0, 0.03, 0.6])
    res = localize(model.template, _scene_of(meshes, 'peg', T, rng), acquisition=model,
                   camera=CAMERA)
    assert res.method == 'acquisition+fine'
    e_t, e_r = symmetric_pose_error(res.pose, T, symmetries['peg'])
    assert e_t < 0.002 and e_r < np.radians(2.0), (e_t, np.degrees(e_r))


def _lying_on_a_table(mesh, R_world, xy, rng, noise=0.001):
    """
    Make a stereo-like scene of ``mesh`` resting on a table.

    A stereo-like scene: ``mesh`` turned by ``R_world`` resting on a table (world z = 0),
    seen from 0.6 m at 50 deg elevation; table samples under the object removed (hidden),
    1 mm noise. Returns the cloud (optical frame) and the true pose model -> optical.
    """
    V = np.asarray(mesh.vertices) @ R_world.T
    T_w = make_transform(R_world, [xy[0], xy[1], -V[:, 2].min()])
    elev = np.radians(50.0)
    # camera on the -y side looking at the origin; optical z forward, x right, y down
    eye = np.array([0.0, -0.6 * np.cos(elev), 0.6 * np.sin(elev)])
    z = -eye / np.linalg.norm(eye)
    x = np.array([1.0, 0.0, 0.0])
    y = np.cross(z, x)
    R_wc = np.stack([x, y, z], axis=1)                      # camera axes in the world
    T_cw = np.linalg.inv(make_transform(R_wc, eye))         # world -> camera
    T = T_cw @ T_w
    P = sample_visible_surface(mesh, T, 30000, seed=int(rng.integers(1 << 30)))
    table = np.stack([rng.uniform(-0.25, 0.25, 40000), rng.uniform(-0.2, 0.2, 40000),
                      np.zeros(40000)], axis=1)
    Vw = V + T_w[:3, 3]
    lo, hi = Vw[:, :2].min(0) - 0.002, Vw[:, :2].max(0) + 0.002
    table = table[~np.all((table[:, :2] >= lo) & (table[:, :2] <= hi), axis=1)]
    table = table @ T_cw[:3, :3].T + T_cw[:3, 3]
    cloud = np.vstack([P, table])
    return cloud + rng.normal(scale=noise, size=cloud.shape), T


@pytest.mark.slow
@pytest.mark.parametrize('name', ['ball_link', 'slider_base'])
def test_acquire_thin_bar_and_rail_lying_on_a_table(name):
    """
    Acquire the thin bar and the low rail lying on a table.

    The thin bar (3 cm x 15 cm) and the low rail (30 x 6 x 2 cm), lying on a table seen
    obliquely (1 mm noise), turned about the vertical: found within 2 mm / 2 deg.
    """
    mesh = load_obj(find_model(name))
    s = sample_model_surface(mesh, 0.003, max_samples=8000)
    sym = find_symmetries(s.points, s.spacing)
    model = prepare_acquisition_model(mesh)
    rng = np.random.default_rng(11)
    # the bar's long axis is its z: lay it down; the rail lies flat already
    base = rotation_about_axis([1.0, 0.0, 0.0], np.pi / 2) if name == 'ball_link' else np.eye(3)
    for yaw in (0.4, 2.0):
        cloud, T = _lying_on_a_table(mesh, rotation_about_axis([0.0, 0.0, 1.0], yaw) @ base,
                                     (0.02, -0.01), rng)
        hyps = acquire_object(model, cloud, camera=CAMERA, seed=2, time_budget_s=30.0)
        e_t, e_r = symmetric_pose_error(hyps[0].pose, T, sym)
        assert e_t < 0.002 and e_r < np.radians(2.0), (name, yaw, e_t, np.degrees(e_r))


@pytest.mark.slow
def test_ppf_references_are_bounded_on_huge_clouds(meshes, monkeypatch):
    """
    Bound the work per cloud.

    Bounded work per cloud: a cloud of 100 000 random points gets at most max_references
    PPF reference points (a longer stride); an object-sized cloud keeps Drost's stride 5.
    """
    import object_localizer.acquisition as acquisition
    model = prepare_acquisition_model(meshes['link_arm'])
    seen = []

    def vote(ppf, S, SN, reference_stride, seed):
        seen.append((len(S), reference_stride))
        return np.zeros((0, 4, 4)), np.zeros(0)
    monkeypatch.setattr(acquisition, 'ppf_vote', vote)
    junk = np.random.default_rng(1).random((100_000, 3)) * 2.0 + [-1.0, -1.0, 0.2]
    assert acquire_object(model, junk, max_references=1000) == []
    samples, stride = seen[-1]
    assert samples > 5000 and -(-samples // stride) <= 1000 and stride > 5
    T = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 0.9), [0.03, -0.02, 0.7])
    acquire_object(model, sample_visible_surface(meshes['link_arm'], T, 6000, seed=3))
    assert seen[-1][1] == 5


def test_same_place_up_to_symmetries_but_not_slid(meshes):
    """A cylinder turned about its axis is the same place; a brick slid 5 mm along itself not."""
    from object_localizer.acquisition import _same_place
    T = make_transform(rotation_about_axis([0.3, 1.0, 0.2], 1.1), [0.02, -0.03, 0.6])
    cyl = prepare_acquisition_model(meshes['cylinder'])
    c = cyl.surface.points.mean(axis=0)
    # the cylinder's axis: the principal axis its samples are spread least evenly about
    for axis in cyl.axes:
        turn = make_transform(rotation_about_axis(axis, 0.9), c) @ make_transform(np.eye(3), -c)
        if _same_place(cyl, T, T @ turn, 0.002):
            break
    else:
        pytest.fail('no turn about a principal axis of the cylinder kept its place')
    arm = prepare_acquisition_model(meshes['link_arm'])
    slid = T.copy()
    slid[:3, 3] += 0.005 * (T[:3, :3] @ arm.axes[0])          # along its length
    assert not _same_place(arm, T, slid, 0.002)
    assert _same_place(arm, T, T, 0.002)
    # turned by 30 deg about its length: not a symmetry of the brick
    c = arm.surface.points.mean(axis=0)
    turned = T @ make_transform(rotation_about_axis(arm.axes[0], np.radians(30.0)), c) @ \
        make_transform(np.eye(3), -c)
    assert not _same_place(arm, T, turned, 0.002)


def test_search_leaves_out_what_a_verified_twin_explains(meshes, symmetries):
    """
    A brick's search with its identical twin verified finds the other place.

    Two identical bricks (link_arm's shape) in one cloud: with one brick's surface given as
    explained (the tracker gives the objects verified in the cloud), the search's poses are all
    off that brick and the first is the other brick within 2 mm / 2 deg, either way round.
    """
    from object_localizer.tracking import make_acquirer, prepare_tracking_model
    rng = np.random.default_rng(8)
    bricks = [make_transform(rotation_about_axis([0.5, -0.3, 1.0], 2.6), [0.05, -0.02, 0.5]),
              make_transform(rotation_about_axis([-0.2, 0.4, 1.0], 0.9), [-0.07, 0.03, 0.62])]
    P = np.vstack([sample_visible_surface(meshes['link_arm'], bricks[0], 30000, seed=1),
                   sample_visible_surface(meshes['link_arm'], bricks[1], 12000, seed=2),
                   _scene_of(meshes, 'link_arm', bricks[0], rng)[30000:]])   # the table
    P = P + rng.normal(scale=0.0005, size=P.shape)
    model = prepare_tracking_model(meshes['link_arm'])
    acquire = make_acquirer('ppf', time_budget_s=30.0, camera=lambda: CAMERA)
    sym = symmetries['link_arm']

    def found(pose, truth):
        e_t, e_r = symmetric_pose_error(pose, truth, sym)
        return e_t < 0.002 and e_r < np.radians(2.0)
    assert any(found(acquire(model, P, 1)[0], T) for T in bricks)
    for k in (0, 1):
        explained = model.points @ bricks[k][:3, :3].T + bricks[k][:3, 3]
        poses = acquire(model, P, 1, (explained, 0.005))
        assert found(poses[0], bricks[1 - k]), [symmetric_pose_error(p, bricks[1 - k], sym)
                                                for p in poses]
        assert not any(found(p, bricks[k]) for p in poses)


def test_symmetric_add_is_zero_for_an_equivalent_pose_where_add_s_has_a_floor(meshes, symmetries):
    """
    The peg turned upside down onto itself: symmetric ADD 0, ADD-S on its voxel template not.

    The peg (40 x 40 x 120 mm, origin on its bottom face) turned 180 deg about a diagonal of
    its cross-section and lifted by its length is the same solid: ``symmetric_add`` is 0, while
    ADD-S on the 3 mm voxel template (not symmetric itself) has a floor of tenths of a mm. A
    real 1 mm shift reads 1 mm.
    """
    from object_localizer.evaluation import add_s
    from object_localizer.localization import prepare_model
    from object_localizer.symmetry import surface_centroid, symmetric_add
    sym = symmetries['peg']
    pts = prepare_model(meshes['peg']).points
    centre = surface_centroid(np.asarray(meshes['peg'].vertices), meshes['peg'].triangles())
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.06], atol=1e-12)
    T = make_transform(rotation_about_axis([0.3, -0.2, 1.0], 0.7), [0.02, -0.01, 0.5])
    flip = make_transform(rotation_about_axis([1.0, 1.0, 0.0], np.pi), [0.0, 0.0, 0.12])
    assert symmetric_add(T @ flip, T, pts, sym, centre=centre) < 1e-9
    assert add_s(T @ flip, T, pts) > 1e-4
    shifted = make_transform(np.eye(3), [0.001, 0.0, 0.0]) @ T
    assert abs(symmetric_add(shifted, T, pts, sym, centre=centre) - 0.001) < 1e-9


def test_a_coarse_pose_is_polished_by_the_trackers_icp():
    """
    A pose 2.6 mm / 2.5 deg off on a stereo cloud is polished to within 1 mm / 0.5 deg.

    prismatic_pair, seed 0, frame 128 of the acquisition benchmark, where the coarse stages
    ended the rail 2.6 mm off along its length and the carriage turned 2.5 deg: those poses,
    made from the truth, are polished by ``polish_hypothesis`` (the tracker's ICP, kept when
    it passes the check no worse); ``acquire_object`` (``polish`` on) ends within 1 mm / 1
    deg of the truth.
    """
    from object_localizer.acquisition import Hypothesis, polish_hypothesis
    from object_localizer.tracking import refine_and_check, TrackerSettings
    pts, camera, truth = _stereo_cloud('prismatic_pair', 128, 0, 112, 48)
    settings = TrackerSettings()
    for name, seed in (('slider_base', 96), ('slider_carriage', 97)):
        mesh = load_obj(find_model(name))
        model = prepare_acquisition_model(mesh)
        s = sample_model_surface(mesh, 0.003, max_samples=8000)
        symmetry = find_symmetries(s.points, s.spacing)
        T = truth['poses'][name]
        axis = model.check.axes[int(np.argmax(model.check.extents))]
        off = T @ (make_transform(np.eye(3), 0.0026 * axis) if name == 'slider_base' else
                   make_transform(rotation_about_axis([0.2, 0.3, 1.0], np.radians(2.5)),
                                  [0.0, 0.0, 0.0]))
        e_t, e_r = symmetric_pose_error(off, T, symmetry)
        assert e_t > 0.002 or e_r > np.radians(2.0), (name, e_t, np.degrees(e_r))
        scene = prepare_acquisition_scene(pts, camera=camera)
        _, q0 = refine_and_check(model.check, scene.rays(), off, settings, acquisition=True,
                                 refine=False)
        h = Hypothesis(off.copy(), 0.0, 'ppf', 0.0, 0.0)
        assert polish_hypothesis(model, scene, h, q0, settings)
        e_t, e_r = symmetric_pose_error(h.pose, T, symmetry)
        assert e_t < 0.001 and e_r < np.radians(0.5), (name, e_t, np.degrees(e_r))
        assert h.score == h.visibility.combined > 0.0
        best = acquire_object(model, prepare_acquisition_scene(pts, camera=camera), seed=seed,
                              time_budget_s=float('inf'))[0]
        e_t, e_r = symmetric_pose_error(best.pose, T, symmetry)
        assert e_t < 0.001 and e_r < np.radians(1.0), (name, e_t, np.degrees(e_r))


def test_nearest_equivalent_pose_turns_the_upside_down_peg_back(meshes, symmetries):
    """
    The upside-down peg, an equivalent pose, is given back in the reference's orientation.

    Of the peg's 8 equivalent poses (4 turns about its long axis, each upright or upside
    down), the one nearest a reference 10 deg from the truth is the truth itself, exactly; the
    surface stays where it was; a pose already near the reference is returned unchanged.
    """
    from object_localizer.symmetry import nearest_equivalent_pose, surface_centroid
    sym = symmetries['peg']
    assert len(sym.rotations) == 8
    centre = surface_centroid(np.asarray(meshes['peg'].vertices), meshes['peg'].triangles())
    T = make_transform(rotation_about_axis([0.3, -0.2, 1.0], 0.7), [0.02, -0.01, 0.5])
    reference = T @ make_transform(rotation_about_axis([0.0, 1.0, 0.2], np.radians(10.0)),
                                   [0.003, 0.0, 0.0])
    for flip in (make_transform(rotation_about_axis([1.0, 1.0, 0.0], np.pi), [0, 0, 0.12]),
                 make_transform(rotation_about_axis([0.0, 0.0, 1.0], np.pi / 2), [0, 0, 0]),
                 make_transform(rotation_about_axis([1.0, 0.0, 0.0], np.pi), [0, 0, 0.12])):
        equivalent = T @ flip
        back = nearest_equivalent_pose(equivalent, reference, sym.rotations, centre)
        np.testing.assert_allclose(back, T, atol=1e-9)
        V = np.asarray(meshes['peg'].vertices)
        moved = V @ back[:3, :3].T + back[:3, 3]
        was = V @ equivalent[:3, :3].T + equivalent[:3, 3]
        from scipy.spatial import cKDTree
        assert cKDTree(was).query(moved)[0].max() < 1e-9      # the same solid, same place
    assert nearest_equivalent_pose(T, reference, sym.rotations, centre) is T


@pytest.mark.parametrize('scene_name,seed,frame,band,name,acquisition_seed', [
    ('peg_in_hole', 0, 144, (48, 112), 'hole_block', 18),
    ('primitives', 1, 157, (48, 80), 'superquadric', 179)])
def test_a_near_tie_of_the_pixel_score_goes_to_the_pose_the_samples_support(
        scene_name, seed, frame, band, name, acquisition_seed):
    """
    Trials of the acquisition benchmark whose best two poses score within 0.015.

    hole_block's equivalent pose 1.7 mm off scored 0.778 against 0.768 for the one 0.1 mm
    off; the superquadric turned 3 deg 0.926 against 0.915 for the one 0.5 deg off. Decided
    by the check's scene support per surface sample (``tie_margin``) the best pose is within
    2 mm / 2 deg of the truth (symmetry-aware); with the pixel score alone (``tie_margin`` 0)
    it is not.
    """
    pts, camera, truth = _stereo_cloud(scene_name, frame, seed, band[1], band[0])
    mesh = load_obj(find_model(name))
    model = prepare_acquisition_model(mesh)
    s = sample_model_surface(mesh, 0.003, max_samples=8000)
    symmetry = find_symmetries(s.points, s.spacing)
    errors = {}
    for margin in (0.015, 0.0):
        best = acquire_object(model, prepare_acquisition_scene(pts, camera=camera),
                              seed=acquisition_seed, time_budget_s=float('inf'),
                              tie_margin=margin)[0]
        e_t, e_r = symmetric_pose_error(best.pose, truth['poses'][name], symmetry)
        errors[margin] = (1e3 * e_t, np.degrees(e_r))
    assert errors[0.015][0] < 2.0 and errors[0.015][1] < 2.0, errors
    assert errors[0.0][0] > 2.0 or errors[0.0][1] > 2.0, errors
