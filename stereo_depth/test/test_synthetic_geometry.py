"""
Geometry acceptance of the synthetic stereo camera.

Exact correspondences, disparity, occlusion, and agreement with an independent ray caster (Open3D).
"""

import numpy as np
import open3d as o3d
import pytest
from stereo_depth.synthetic import (
    look_at, make_scene, render, RenderOptions, reprojection_errors, SCENES, StereoCamera,
    StereoRenderer)
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.transforms import invert_transform, make_transform, rotation_about_axis

FRAMES = [('peg_in_hole', 10), ('peg_in_hole', 60), ('peg_in_hole', 100),
          ('peg_in_hole', 150), ('peg_in_hole', 200), ('peg_in_slot', 100),
          ('revolute_pair', 37), ('prismatic_pair', 80), ('spherical_pair', 120),
          ('primitives', 45)]


@pytest.mark.parametrize('scene,frame', FRAMES)
def test_left_depth_reprojects_onto_same_surface_point_in_right(scene, frame):
    _, _, truth = render(scene, frame, seed=7)
    errs = reprojection_errors(truth)
    assert len(errs) >= 200, f'only {len(errs)} testable pixels'
    assert errs.max() < 0.05, f'max reprojection error {errs.max():.4f} px'


def test_reprojection_check_detects_a_wrong_baseline():
    """The acceptance check is not vacuous: a 1 % baseline error is caught."""
    _, _, truth = render('peg_in_hole', 150, seed=7)
    bad = dict(truth)
    cam = dict(truth['camera'])
    cam['P_right'] = cam['P_right'].copy()
    cam['P_right'][0, 3] *= 1.01
    bad['camera'] = cam
    assert reprojection_errors(bad).max() > 0.2


@pytest.mark.parametrize('scene', SCENES)
def test_disparity_is_fx_b_over_z_and_background_marked(scene):
    left, right, truth = render(scene, 33, seed=1)
    cam = truth['camera']
    d, z = truth['disparity'], truth['depth']
    valid = truth['valid']
    assert left.shape == right.shape == (480, 640) and left.dtype == np.uint8
    np.testing.assert_array_equal(valid, np.isfinite(z))
    np.testing.assert_array_equal(valid, np.isfinite(d))
    expected = cam['fx'] * cam['baseline'] / z[valid].astype(np.float64)
    np.testing.assert_allclose(d[valid], expected, rtol=2e-7)
    assert np.all(truth['object_id'][~valid] == -1) and np.all(truth['face_id'][~valid] == -1)
    assert not truth['occlusion'][~valid].any()
    assert np.all(np.isnan(truth['texcoords'][~valid]))
    # Working range of the chapter: objects 0.5-1.5 m away -> plausible disparities.
    obj = valid & (truth['object_id'] != truth['object_names'].index('table'))
    assert obj.any()
    assert 0.25 < np.nanmin(z[obj]) and np.nanmax(z[obj]) < 1.5


def test_left_border_is_marked_out_of_view():
    _, _, truth = render('peg_in_hole', 0, seed=2)
    H, W = truth['depth'].shape
    u = np.arange(W)[None, :].repeat(H, 0)
    out = truth['valid'] & (u - truth['disparity'] < -0.5)
    assert out.sum() > 1000
    assert truth['occlusion'][out].all()


def _ray_box_hit(origins, dirs, lo, hi):
    """Entry parameter of rays into an axis-aligned box (inf if missed), slab method."""
    with np.errstate(divide='ignore', invalid='ignore'):
        t1 = (lo - origins) / dirs
        t2 = (hi - origins) / dirs
    tmin = np.nanmax(np.minimum(t1, t2), axis=1)
    tmax = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((tmax >= tmin) & (tmax > 0), tmin, np.inf)


def test_occlusion_mask_matches_analytic_box_occluder():
    """
    A cube floating in front of a wall.

    a wall point is occluded iff the segment from it to the right optical centre enters the cube
    (computed here analytically).
    """
    cam = StereoCamera.create(width=320, height=240, fx=300.0, baseline=0.1)
    table, cube = load_obj(find_model('table')), load_obj(find_model('cube'))
    r = StereoRenderer(cam, [table, cube], seed=3)
    # Table as a wall facing the camera 1.0 m away; cube axis-aligned, centred 0.6 m away.
    wall = make_transform(rotation_about_axis(np.array([1.0, 0, 0]), np.pi), [0, 0, 1.0])
    poses = {'table': wall, 'cube': make_transform(np.eye(3), [0.02, 0.01, 0.6])}
    _, _, truth = r.render(poses)
    wall_px = truth['object_id'] == 0
    vs, us = np.nonzero(wall_px)
    X = cam.back_project(us, vs, truth['depth'][vs, us].astype(np.float64))
    C = cam.right_center
    t = _ray_box_hit(X, C - X, np.array([-0.02, -0.03, 0.56]), np.array([0.06, 0.05, 0.64]))
    hidden = (t > 1e-9) & (t < 1.0)
    ur = us - truth['disparity'][vs, us]
    expected = hidden | (ur < -0.5)
    got = truth['occlusion'][vs, us]
    assert expected.sum() > 500
    assert np.sum(got != expected) <= 2, f'{np.sum(got != expected)} pixels differ'
    # The occluded band lies just left of the cube, as the rectified geometry requires.
    cube_cols = np.nonzero((truth['object_id'] == 1).any(0))[0]
    band = truth['occlusion'][:, 60:cube_cols.min()].any(0)
    assert band.any()


def _open3d_depth(renderer, poses, cam, origin_x):
    sc = o3d.t.geometry.RaycastingScene()
    for name, T in poses.items():
        m = renderer.models[renderer.names.index(name)]
        V = (m.vertices @ T[:3, :3].T + T[:3, 3]).astype(np.float32)
        sc.add_triangles(o3d.core.Tensor(V), o3d.core.Tensor(m.tris.astype(np.uint32)))
    d = cam.ray_directions().reshape(-1, 3)
    rays = np.concatenate([np.zeros_like(d), d], 1)
    rays[:, 0] = origin_x
    t = sc.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))['t_hit'].numpy()
    return t.reshape(cam.height, cam.width)


@pytest.mark.parametrize('scene,frame', [('peg_in_hole', 70), ('primitives', 10),
                                         ('spherical_pair', 200)])
def test_depth_equals_open3d_raycasting(scene, frame):
    s = make_scene(scene, seed=5)
    cam = StereoCamera.create()
    meshes = [load_obj(find_model(n)) for n in s.objects]
    r = StereoRenderer(cam, meshes, seed=5)
    poses = s.poses(frame)
    _, _, truth = r.render(poses)
    for key, ox in (('depth', 0.0), ('depth_right', cam.baseline)):
        ref = _open3d_depth(r, poses, cam, ox)
        mine = truth[key]
        hit_ref, hit = np.isfinite(ref), np.isfinite(mine)
        # Pixels whose ray grazes a silhouette edge may differ between float32 and float64.
        assert np.sum(hit_ref != hit) <= 3
        both = hit_ref & hit
        rel = np.abs(ref[both] - mine[both]) / ref[both]
        assert np.percentile(rel, 99.9) < 1e-5


def test_render_is_deterministic_and_seed_dependent():
    opts = RenderOptions(noise_sigma=2.0, gain_right=1.1, blur_sigma=0.5)
    a = render('revolute_pair', 12, seed=4, options=opts)
    b = render('revolute_pair', 12, seed=4, options=opts)
    c = render('revolute_pair', 12, seed=5, options=opts)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    for k in a[2]['poses']:
        np.testing.assert_array_equal(a[2]['poses'][k], b[2]['poses'][k])
    assert not np.array_equal(a[0], c[0])


def test_texture_moves_with_the_object():
    """Same object pose relative to the camera -> same image, whatever the world placement."""
    cam = StereoCamera.create(width=200, height=150, fx=200.0)
    cube = load_obj(find_model('cube'))
    r = StereoRenderer(cam, [cube], seed=9)
    T = make_transform(rotation_about_axis(np.array([1.0, 2, 3]), 0.7), [0.0, 0.0, 0.5])
    l1, _, t1 = r.render({'cube': T})
    T2 = make_transform(rotation_about_axis(np.array([1.0, 2, 3]), 0.9), [0.0, 0.0, 0.5])
    l2, _, t2 = r.render({'cube': T2})
    assert not np.array_equal(l1, l2)
    # Rendering the object at T2 gives texcoords consistent with its own charts: for every
    # pixel, (s, t) = A_f X_obj + b_f with X_obj the back-projected point in the cube frame.
    vs, us = np.nonzero(t2['valid'])
    X = cam.back_project(us, vs, t2['depth'][vs, us].astype(np.float64))
    Xo = (X - T2[:3, 3]) @ T2[:3, :3]
    A, b = r.charts['cube']
    f = t2['face_id'][vs, us]
    st = np.einsum('nij,nj->ni', A[f], Xo) + b[f]
    np.testing.assert_allclose(st, t2['texcoords'][vs, us], atol=0.02)


def test_bad_inputs_raise_clear_errors():
    with pytest.raises(ValueError, match='unknown scene'):
        render('no_such_scene', 0)
    with pytest.raises(ValueError, match='fx'):
        StereoCamera.create(fx=0.0)
    with pytest.raises(ValueError, match='baseline'):
        StereoCamera.create(baseline=-0.1)
    with pytest.raises(ValueError, match='noise_sigma'):
        RenderOptions(noise_sigma=-1.0)
    cam = StereoCamera.create(width=64, height=48, fx=60.0)
    r = StereoRenderer(cam, [load_obj(find_model('cube'))])
    with pytest.raises(KeyError, match='no model'):
        r.render({'sphere': np.eye(4)})
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(ValueError):
        r.render({'cube': bad})


def test_rgb_and_photometric_options():
    opts = RenderOptions(color=True, gain_right=1.2)
    left, right, truth = render('primitives', 3, seed=1, options=opts)
    assert left.shape == (480, 640, 3) and right.dtype == np.uint8
    m = truth['valid'] & ~truth['occlusion']
    assert right[m].mean() > left[m].mean() * 1.05


def test_look_at_gives_optical_frame():
    T = look_at(np.array([0.0, -1.0, 0.0]), np.zeros(3))
    np.testing.assert_allclose(T[:3, 2], [0, 1, 0], atol=1e-12)   # z forward
    np.testing.assert_allclose(T[:3, 0], [1, 0, 0], atol=1e-12)   # x right
    np.testing.assert_allclose(T[:3, 1], [0, 0, -1], atol=1e-12)  # y down
    T_cw = invert_transform(T)
    assert (T_cw @ [0, 0, 0, 1])[2] == pytest.approx(1.0)


@pytest.mark.parametrize('scene', ['peg_in_hole', 'primitives', 'revolute_pair'])
def test_cached_static_layer_gives_identical_output(scene):
    """
    Rendering the static objects once and reusing them changes nothing.

    Rendering the static objects once and reusing them changes nothing, also when the
    static poses change between calls (the cache is keyed by the exact poses).
    """
    s = make_scene(scene, seed=2)
    cam = StereoCamera.create(width=320, height=240, fx=300.0)
    meshes = [load_obj(find_model(n)) for n in s.objects]
    cached = StereoRenderer(cam, meshes, seed=2, options=RenderOptions(noise_sigma=1.0))
    full = StereoRenderer(cam, meshes, seed=2, options=RenderOptions(noise_sigma=1.0))
    assert s.static
    for k in (0, 40, 41):
        poses = s.poses(k)
        if k == 41:  # move a "static" object: the cache must notice
            poses['table'] = poses['table'] @ make_transform(np.eye(3), [0.01, 0.0, 0.0])
        a = cached.render(poses, noise_key=(k,), static=s.static)
        b = full.render(poses, noise_key=(k,))
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        for key in ('depth', 'disparity', 'occlusion', 'object_id', 'face_id', 'texcoords',
                    'depth_right', 'object_id_right', 'face_id_right', 'texcoords_right'):
            np.testing.assert_array_equal(a[2][key], b[2][key], err_msg=key)


@pytest.mark.parametrize('scene', ['peg_in_hole', 'revolute_pair'])
def test_images_only_render_gives_the_same_pair(scene):
    """Rendering without truth images (the live camera's default) gives the same pair."""
    s = make_scene(scene, seed=3)
    cam = StereoCamera.create(width=320, height=240, fx=300.0)
    meshes = [load_obj(find_model(n)) for n in s.objects]
    lean = StereoRenderer(cam, meshes, seed=3, options=RenderOptions(noise_sigma=1.0))
    full = StereoRenderer(cam, meshes, seed=3, options=RenderOptions(noise_sigma=1.0))
    for k in (0, 7, 30, 7):      # the reused buffers must not leak one frame into the next
        poses = s.poses(k)
        a = lean.render(poses, noise_key=(k,), static=s.static, images_only=True)
        b = full.render(poses, noise_key=(k,), static=s.static)
        np.testing.assert_array_equal(a[0], b[0])
        np.testing.assert_array_equal(a[1], b[1])
        assert sorted(a[2]) == ['camera', 'object_names', 'poses']
        assert sorted(a[2]['poses']) == sorted(b[2]['poses'])
        for name, T in b[2]['poses'].items():
            np.testing.assert_array_equal(a[2]['poses'][name], T)
    c = lean.render(s.poses(30), noise_key=(30,), static=s.static)   # and back to full truth
    d = full.render(s.poses(30), noise_key=(30,), static=s.static)
    for key in ('depth', 'occlusion', 'object_id', 'texcoords', 'depth_right'):
        np.testing.assert_array_equal(c[2][key], d[2][key], err_msg=key)
