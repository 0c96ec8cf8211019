"""
Benchmark: global acquisition (no initial pose) on the stereo clouds of every synthetic scene.

Data: every scene of ``stereo_depth.synthetic`` (peg_in_hole, peg_in_slot, revolute_pair,
prismatic_pair, spherical_pair, primitives), ``--frames`` frames each spread over the scene's
sequence and over scene seeds; each frame rendered as a stereo pair and run through the stereo
pipeline the demo uses (``block_matching`` over the scene's disparity band,
``stereo_manip_bringup.demo.SCENE_DISPARITY_BANDS``: the scene's depth range; full resolution)
-> the organised point cloud of the left camera (partial views, stereo noise, fill at borders,
table and the other objects in view). Every object of the scene but the table is searched in
the full cloud from nothing: one trial per (frame, object).

Methods, all on the same clouds in this run:
- ``ppf``: ours, point-pair-feature voting (Drost et al. 2010) -> visibility verification ->
  M-estimator ICP -> verification (object_localizer.acquisition, method='ppf');
- ``fpfh``: ours with the FPFH + RANSAC rough stage (method='fpfh'), same verification + ICP;
- ``localize``: the previous global search, object_localizer.localization.localize;
- ``open3d_fpfh_ransac``: the peer, plain Open3D: FPFH + RANSAC (registration_ransac_based_on_
  feature_matching) then Open3D point-to-plane ICP, no verification.

The node path, in the same run on the same clouds (``node``; ``--no-node`` skips it): each
cloud once through an in-process ``ObjectLocalizerNode`` (its defaults, the scene's objects as
``models``, no initial poses, the left CameraInfo of the cloud's frame; the cloud as the demo's
stereo node publishes it: every 2nd pixel, ``--node-decimation``) -- what a user gets
from a node started on that view: the global search, the tracker's ICP and quality check, the
ambiguity and identical-part rules, the overlap rule between objects found in one cloud. Per
object: a pose published (scored like the others, and a wrong one = ADD-S over 5 mm) or the
reason none was. Identical parts (``link_base``, ``link_arm``) are never named without a hint:
counted as not published.

Error: symmetry-aware (object_localizer.symmetry): centroid translation error and the smallest
rotation error over the model's symmetry group (continuous axes included); success = within
2 mm and 2 deg. ADD-S is reported as well. ``link_base`` and ``link_arm`` are the same brick
(identical meshes up to their frames): in the revolute scene, a pose on the other brick is a
correct detection of that shape that no method can attribute from geometry alone, so those two
are scored against the nearer of the two truths (``success``); ``success_strict`` scores
against the named object only, and both rates are reported. Times: wall time per object
including the scene preparation (down-sampling, normals, plane removal, observed depth) that a
multi-object search would share. Accuracy runs may use the shared CPU lock (their times are
then inflated by the load); ``--timing-only N`` re-times N trials (run it under the exclusive
lock) and merges those times into the existing JSON; the time goal uses them when present.

Writes bench/results/localizer_acquisition.json. Clouds are cached in ``--cache`` (not
committed; rebuilt in a few minutes).
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import time

import numpy as np
from object_localizer.acquisition import (acquire_object, prepare_acquisition_model,
                                          prepare_acquisition_scene)
from object_localizer.evaluation import add_s
from object_localizer.localization import (fpfh_features, localize, match_features_ransac,
                                           prepare_scene, remove_dominant_plane)
from object_localizer.symmetry import find_symmetries, symmetric_pose_error
from object_localizer.verification import (observe_depth, sample_model_surface,
                                           score_pose_visibility)
import open3d as o3d
from stereo_manip_bringup.demo import SCENE_DISPARITY_BANDS
from stereo_manip_tools.bench_report import goal, results_dir, write_report
from stereo_manip_tools.mesh_io import find_model, load_obj

SCENES = ('peg_in_hole', 'peg_in_slot', 'revolute_pair', 'prismatic_pair', 'spherical_pair',
          'primitives')
METHODS = ('ppf', 'fpfh', 'localize', 'open3d_fpfh_ransac')
TOL_T, TOL_R = 0.002, np.radians(2.0)
# link_base and link_arm are the same 0.128 x 0.032 x 0.0192 brick; their frames differ by a
# shift: link_base's origin is the centre of its top face, link_arm's the centre of its bottom
# face 0.016 m from one end (make_models._joint_models): the same brick point has coordinates
# p_arm = p_base + (0.048, 0, 0.0192). TWIN_OFFSET[(twin, name)] maps name's frame into twin's.
TWINS = {'link_base': ('link_arm',), 'link_arm': ('link_base',)}
TWIN_OFFSET = {
    ('link_arm', 'link_base'): np.array([[1, 0, 0, 0.048], [0, 1, 0, 0],
                                         [0, 0, 1, 0.0192], [0, 0, 0, 1.0]]),
    ('link_base', 'link_arm'): np.array([[1, 0, 0, -0.048], [0, 1, 0, 0],
                                         [0, 0, 1, -0.0192], [0, 0, 0, 1.0]])}


def stereo_frames(cache: Path, frames_per_scene: int):
    """(scene, seed, frame, points (H, W, 3), camera dict, poses) for every benchmark frame."""
    from stereo_depth.pipeline import compute_disparity, disparity_to_points
    from stereo_depth.synthetic import make_scene, render, StereoCamera
    cache.mkdir(parents=True, exist_ok=True)
    for scene_name in SCENES:
        n_frames = make_scene(scene_name).n_frames
        dmin, count = SCENE_DISPARITY_BANDS[scene_name]
        for k in range(frames_per_scene):
            seed = k % 3
            frame = int((k * n_frames) // frames_per_scene + 7 * seed) % n_frames
            path = cache / f'{scene_name}_s{seed}_f{frame}_d{dmin}_{count}.npz'
            if path.exists():
                data = np.load(path, allow_pickle=True)
                camera = data['camera'].item()
                # clouds cached before the baseline was stored: render()'s default camera
                camera.setdefault('baseline', StereoCamera.create().baseline)
                yield scene_name, seed, frame, data['points'], camera, data['poses'].item()
                continue
            left, right, truth = render(scene_name, frame, seed=seed)
            cam = truth['camera']
            disp = compute_disparity(left, right, 'block_matching', count, min_disparity=dmin)
            pts = disparity_to_points(disp, cam['fx'], cam['fy'], cam['cx'], cam['cy'],
                                      cam['baseline'])
            # the baseline lets the visibility score know what stereo can measure
            camera = {k2: cam[k2] for k2 in ('fx', 'fy', 'cx', 'cy', 'width', 'height',
                                             'baseline')}
            poses = {n: np.asarray(T) for n, T in truth['poses'].items() if n != 'table'}
            np.savez_compressed(path, points=pts.astype(np.float32), camera=camera, poses=poses)
            yield scene_name, seed, frame, pts, camera, poses


def open3d_peer(template, points, seed):
    """
    Localise with plain Open3D (the peer).

    FPFH + RANSAC on the scene without its dominant plane, then point-to-plane ICP (least squares).
    """
    reg = o3d.pipelines.registration
    v = template.voxel_size
    search = prepare_scene(points, v)
    diameter = float(np.linalg.norm(template.points.max(0) - template.points.min(0)))
    search = remove_dominant_plane(search, v, 2.0 * diameter, seed=seed)
    rough, _ = match_features_ransac(template, search, fpfh_features(search, v), seed=seed,
                                     max_iterations=100000, confidence=0.999)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        icp = reg.registration_icp(template.cloud, search, 2.0 * v, rough,
                                   reg.TransformationEstimationPointToPlane(),
                                   reg.ICPConvergenceCriteria(1e-6, 1e-6, 50))
    return np.asarray(icp.transformation)


def run_method(method, model, points, camera, seed, final_check=False):
    finite = points.reshape(-1, 3)
    finite = finite[np.all(np.isfinite(finite), axis=1)]
    t0 = time.perf_counter()
    if method in ('ppf', 'fpfh'):
        scene = prepare_acquisition_scene(points, camera=camera)
        hyps = acquire_object(model, scene, method=method, seed=seed, time_budget_s=float('inf'),
                              final_check=final_check)
        pose = hyps[0].pose if hyps else np.eye(4)
        score = hyps[0].score if hyps else 0.0
    elif method == 'localize':
        pose = localize(model.template, finite, seed=seed).pose
        score = float('nan')
    else:
        pose = open3d_peer(model.template, finite, seed)
        score = float('nan')
    return pose, time.perf_counter() - t0, score


FRAME = 'left_camera_optical_frame'


def node_outcomes(points, camera, names):
    """
    Run one cloud through a fresh in-process ``ObjectLocalizerNode`` with node defaults.

    :return: {object: TrackUpdate published for it}, process CPU [s] and wall time [s] of the
        cloud (every object's search).
    """
    import rclpy
    from rclpy.parameter import Parameter
    from std_msgs.msg import Header
    from object_localizer.localizer_node import ObjectLocalizerNode
    from stereo_manip_tools.conversions import (camera_info_from_parameters,
                                                StereoCameraParameters, xyz_to_pointcloud2)
    if not rclpy.ok():
        rclpy.init()
    node = ObjectLocalizerNode(parameter_overrides=[Parameter('models', value=list(names))])
    left, _ = camera_info_from_parameters(
        StereoCameraParameters(fx=camera['fx'], fy=camera['fy'], cx=camera['cx'],
                               cy=camera['cy'], baseline=camera['baseline'],
                               width=int(camera['width']), height=int(camera['height'])),
        Header(frame_id=FRAME))
    node._on_camera_info(left)
    outcomes = {}
    original = node._publish

    def publish(name, result, *rest):
        outcomes[name] = result
        original(name, result, *rest)
    node._publish = publish
    msg = xyz_to_pointcloud2(np.asarray(points, dtype=np.float32).reshape(-1, 3))
    msg.header.frame_id = FRAME
    msg.header.stamp.sec = 1
    node._cloud_frame = FRAME
    c0, t0 = time.process_time(), time.perf_counter()
    node._process(msg)
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    node.destroy_node()
    return outcomes, cpu, wall


def observability(model, points, camera, truth, chosen):
    """
    Diagnose a trial: how much of the object the stereo cloud shows, and which pose scores more.

    The true pose is scored against the observed depth like any hypothesis (4 mm tolerance):
    ``truth_inlier_fraction`` is the share of its expected-visible pixels where the stereo
    depth is within 4 mm of the model (0 = the sensor does not see the object where it is, e.g.
    nearer than the stereo's minimum depth), ``truth_combined`` / ``chosen_combined`` the
    ranking scores of the truth and of the returned pose (chosen > truth: the score prefers a
    wrong pose; truth > chosen: the right pose was not generated or lost in refinement).
    """
    observed = observe_depth(points, camera)
    vt = score_pose_visibility(model.surface, truth, observed, inlier_threshold=0.004)
    vc = score_pose_visibility(model.surface, chosen, observed, inlier_threshold=0.004)
    return {'truth_inlier_fraction': vt.inlier_fraction,
            'truth_violation_fraction': vt.violation_fraction,
            'truth_occluded_fraction': vt.occluded_fraction,
            'truth_unknown_fraction': vt.unknown_fraction,
            'truth_edge_fraction': vt.edge_fraction,
            'truth_combined': vt.combined, 'chosen_combined': vc.combined}


def diagnose(failures):
    """
    Count the failures per object by cause (see :func:`observability`).

    ``sensor``: less than half of the true pose's visible surface is in the stereo cloud
    (truth_inlier_fraction < 0.5); ``score``: the returned wrong pose scores at least as high
    as the truth (the verification prefers it); ``search``: the truth scores higher (the right
    pose was not generated, or lost in refinement).
    """
    out = {}
    for r in failures:
        o = r.get('observability')
        if o is None:
            continue
        cause = 'sensor' if o['truth_inlier_fraction'] < 0.5 else \
            'score' if o['chosen_combined'] >= o['truth_combined'] else 'search'
        counts = out.setdefault(r['object'], {'sensor': 0, 'score': 0, 'search': 0})
        counts[cause] += 1
    return out


def pose_error(pose, name, poses, symmetries, sym_sets):
    """
    Symmetry-aware error of ``name``'s ``pose`` against the truth ``poses``.

    :return: translation error [m], rotation error [rad] (against the nearer truth of the
        object and its identical twin) and whether it is within tolerance of the named
        object's own truth.
    """
    e_t, e_r = symmetric_pose_error(pose, poses[name], symmetries[name], sym_sets[name])
    strict = bool(e_t <= TOL_T and e_r <= TOL_R)
    for twin in TWINS.get(name, ()):
        if twin in poses:
            # the twin's truth, expressed for this model's frame
            Tt = poses[twin] @ TWIN_OFFSET[(twin, name)]
            et2, er2 = symmetric_pose_error(pose, Tt, symmetries[name], sym_sets[name])
            if max(et2 / TOL_T, er2 / TOL_R) < max(e_t / TOL_T, e_r / TOL_R):
                e_t, e_r = et2, er2
    return e_t, e_r, strict


def published_cloud(points: np.ndarray, decimation: int) -> np.ndarray:
    """
    Return the cloud the stereo node of the graph publishes from the grid ``points``.

    Every ``decimation``-th pixel in both directions of the (H, W, 3) grid [m], only the finite
    points, in raster order (an unorganised cloud): the stereo node's ``point_decimation`` with
    ``organized_cloud`` false, as the demo runs it.
    """
    P = np.asarray(points)
    if P.ndim == 3:
        P = P[::decimation, ::decimation]
    P = P.reshape(-1, 3)
    return P[np.all(np.isfinite(P), axis=1)]


def node_pass(trials, poses_of, models, symmetries, sym_sets, decimation=2):
    """Every cloud of the trials once through the node (:func:`node_outcomes`), scored."""
    rows, clouds = [], {}
    for i, (scene_name, seed, frame, _, pts, camera, _) in enumerate(trials):
        clouds.setdefault((scene_name, seed, frame), (pts, camera, poses_of[i]))
    per_cloud = []
    for (scene_name, seed, frame), (pts, camera, poses) in clouds.items():
        outcomes, cpu, wall = node_outcomes(published_cloud(pts, decimation), camera,
                                            sorted(poses))
        per_cloud.append({'scene': scene_name, 'seed': seed, 'frame': frame,
                          'objects': len(poses), 'cpu_s': cpu, 'wall_s': wall})
        for name in sorted(poses):
            r = outcomes.get(name)
            row = {'scene': scene_name, 'seed': seed, 'frame': frame, 'object': name,
                   'published': bool(r is not None and r.pose is not None),
                   'reason': 'no outcome' if r is None else r.reason[:300],
                   'quality': None if r is None or r.quality is None
                   else r.quality.quality}
            if row['published']:
                e_t, e_r, strict = pose_error(r.pose, name, poses, symmetries, sym_sets)
                row.update(t_err_m=e_t, r_err_deg=float(np.degrees(e_r)),
                           add_s_m=add_s(r.pose, poses[name], models[name].template.points),
                           success=bool(e_t <= TOL_T and e_r <= TOL_R), success_strict=strict)
            else:
                row.update(success=False, success_strict=False)
            rows.append(row)
            print('node', scene_name, seed, frame, name,
                  (round(1e3 * row['t_err_m'], 2), round(row['r_err_deg'], 2))
                  if row['published'] else row['reason'][:100], flush=True)
    return {'records': rows, 'clouds': per_cloud}


def node_summary(node):
    """Success, published, wrong and unpublished-by-cause figures of :func:`node_pass`."""
    rows, clouds = node['records'], node['clouds']
    published = [r for r in rows if r['published']]

    def cause(reason):
        for key, label in (('withdrawn', 'withdrawn (overlaps a better pose)'),
                           ('the same shape as', 'identical part without a hint'),
                           ('ambiguous', 'ambiguous (several places fit)'),
                           ('acquisition failed', 'check failed (no pose passed)')):
            if key in reason:
                return label
        return 'other'
    causes = {}
    for r in rows:
        if not r['published']:
            causes[cause(r['reason'])] = causes.get(cause(r['reason']), 0) + 1
    return {
        'trials': len(rows), 'clouds': len(clouds),
        'success_rate': float(np.mean([r['success'] for r in rows])),
        'published_fraction': len(published) / len(rows),
        'success_rate_of_published': float(np.mean([r['success'] for r in published])),
        'published_over_5mm_add_s': int(sum(r['add_s_m'] > 0.005 for r in published)),
        'published_beyond_2mm_2deg': int(sum(not r['success'] for r in published)),
        'add_s_m_published': stats([r['add_s_m'] for r in published]),
        'translation_error_m_published': stats([r['t_err_m'] for r in published]),
        'not_published_by_cause': causes,
        'cpu_s_per_cloud': stats([c['cpu_s'] for c in clouds]),
        'cpu_s_per_object': stats([c['cpu_s'] / c['objects'] for c in clouds]),
        'wall_s_per_cloud': stats([c['wall_s'] for c in clouds]),
        'success_rate_per_object': {
            n: float(np.mean([r['success'] for r in rows if r['object'] == n]))
            for n in dict.fromkeys(r['object'] for r in rows)},
    }


def stats(values):
    v = np.asarray(values, dtype=float)
    return {'median': float(np.median(v)), 'p95': float(np.percentile(v, 95)),
            'max': float(np.max(v))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    parser.add_argument('--frames', type=int, default=14, help='frames per scene')
    parser.add_argument('--methods', nargs='+', default=list(METHODS), choices=METHODS)
    parser.add_argument('--strides', nargs='+', type=int, default=[1, 6, 21, 3],
                        help='per method (order of --methods): run it on every k-th trial '
                             '(the FPFH-based searches take 10-70 s per trial on the full '
                             'stereo clouds of a loaded 2-core machine)')
    parser.add_argument('--cache', type=Path,
                        default=Path(os.environ.get('TMPDIR', '/tmp')) / 'localizer_acq_cache')
    parser.add_argument('--timing-only', type=int, default=0, metavar='N',
                        help='re-time N trials per method (exclusive lock) and merge the times '
                             'into the existing JSON')
    parser.add_argument('--out', default='localizer_acquisition')
    parser.add_argument('--final-check', action='store_true',
                        help="acquire_object(final_check=True): polish by the tracker's ICP and "
                             "rank by the tracker's check x the pixel score")
    parser.add_argument('--node-decimation', type=int, default=2,
                        help="the node path's clouds: every n-th pixel of the stereo grid, as "
                             "the stereo node's point_decimation publishes them (the demo's "
                             '2; 1: full resolution, which the node voxel-downsamples to its '
                             'max_points)')
    parser.add_argument('--no-node', action='store_true',
                        help='skip the node path (every cloud through ObjectLocalizerNode)')
    parser.add_argument('--rewrite', action='store_true',
                        help='recompute the goals of the existing JSON from its stored '
                             'measurements (no new measurement)')
    args = parser.parse_args()
    if args.rewrite:
        data = json.loads((results_dir() / f'{args.out}.json').read_text())
        args.methods = list(data['summary'])
        return write(args, data['records'], data['summary'], data['success_rate_per_object'],
                     data.get('timing_exclusive_lock'), data.get('node_path'))

    models, symmetries, sym_sets = {}, {}, {}
    trials, poses_of = [], []
    for scene_name, seed, frame, pts, camera, poses in stereo_frames(args.cache, args.frames):
        for name, T in poses.items():
            if name not in models:
                mesh = load_obj(find_model(name))
                models[name] = prepare_acquisition_model(mesh)
                s = sample_model_surface(mesh, 0.003, max_samples=8000)
                symmetries[name] = find_symmetries(s.points, s.spacing)
                sym_sets[name] = symmetries[name].rotation_set()
            trials.append((scene_name, seed, frame, name, pts, camera, T))
            poses_of.append(poses)
    n_clouds = len({(t[0], t[1], t[2]) for t in trials})
    print(f'{len(trials)} trials on {n_clouds} clouds', flush=True)
    strides = dict(zip(args.methods, args.strides + [1] * len(args.methods)))
    if args.timing_only:
        return timing_only(args, trials, models)
    records = []
    for i, (scene_name, seed, frame, name, pts, camera, T) in enumerate(trials):
        rec = {'scene': scene_name, 'seed': seed, 'frame': frame, 'object': name}
        for method in args.methods:
            if i % strides[method]:
                continue
            c0 = time.process_time()
            pose, dt, score = run_method(method, models[name], pts, camera, i,
                                         args.final_check)
            cpu = time.process_time() - c0
            e_t, e_r, strict = pose_error(pose, name, poses_of[i], symmetries, sym_sets)
            if method == 'ppf':
                rec['observability'] = observability(models[name], pts, camera, T, pose)
            rec[method] = {'t_err_m': e_t, 'r_err_deg': float(np.degrees(e_r)),
                           'add_s_m': add_s(pose, T, models[name].template.points),
                           'time_s': dt, 'cpu_s': cpu, 'load_1min': os.getloadavg()[0],
                           'score': score, 'success_strict': strict,
                           'success': bool(e_t <= TOL_T and e_r <= TOL_R)}
        records.append(rec)
        print(i, scene_name, frame, name, {m: (round(rec[m]['t_err_m'] * 1000, 2),
                                               round(rec[m]['r_err_deg'], 2),
                                               round(rec[m]['time_s'], 3))
                                           for m in args.methods if m in rec}, flush=True)
    summary = {}
    for method in args.methods:
        rs = [r[method] for r in records if method in r]
        summary[method] = {
            'trials': len(rs), 'trial_stride': strides[method],
            'success_rate': float(np.mean([r['success'] for r in rs])),
            'success_rate_strict_names': float(np.mean([r['success_strict'] for r in rs])),
            'translation_error_m': stats([r['t_err_m'] for r in rs]),
            'rotation_error_deg': stats([r['r_err_deg'] for r in rs]),
            'add_s_m': stats([r['add_s_m'] for r in rs]),
            'time_s': stats([r['time_s'] for r in rs]),
            # process CPU time (all threads: the numba voting runs on both cores) and the
            # 1-min load average at each trial: the machine is shared, wall times are contended
            'cpu_time_s': stats([r['cpu_s'] for r in rs]) if all('cpu_s' in r for r in rs)
            else None,
            'load_1min': stats([r['load_1min'] for r in rs]) if all('load_1min' in r for r in rs)
            else None,
            'failures': [{k: r[k] for k in ('scene', 'seed', 'frame', 'object')}
                         | {'t_err_m': r[method]['t_err_m'], 'r_err_deg': r[method]['r_err_deg']}
                         | ({'observability': r['observability']}
                            if method == 'ppf' and 'observability' in r else {})
                         for r in records if method in r and not r[method]['success']],
        }
    if 'ppf' in summary:
        summary['ppf']['failure_diagnosis'] = diagnose(
            [r for r in records if 'ppf' in r and not r['ppf']['success']])
    per_object = {}
    for name in models:
        per_object[name] = {m: float(np.mean([r[m]['success'] for r in records
                                              if r['object'] == name and m in r]))
                            for m in args.methods
                            if any(r['object'] == name and m in r for r in records)}
    node = None
    if not args.no_node:
        node = node_pass(trials, poses_of, models, symmetries, sym_sets,
                         args.node_decimation)
        node['decimation'] = args.node_decimation
    write(args, records, summary, per_object, timing=None, node=node)


def write(args, records, summary, per_object, timing, node=None):
    best = 'ppf' if 'ppf' in summary else args.methods[0]
    timing_src = timing if timing is not None else {m: summary[m]['time_s'] for m in summary}
    goals = [
        goal(f'{best}_success_rate_within_2mm_2deg_symmetry_aware', 0.99, '>=',
             summary[best]['success_rate']),
        goal(f'{best}_time_per_object_median_s', 0.5, '<=', timing_src[best]['median']),
        goal(f'{best}_time_per_object_p95_s', 0.5, '<=', timing_src[best]['p95']),
        goal('trials', 200, '>=', len(records)),
    ]
    paired = {}
    for peer in summary:
        if peer == best:
            continue
        both = [r for r in records if peer in r and best in r]
        paired[peer] = {'trials': len(both),
                        best: float(np.mean([r[best]['success'] for r in both])),
                        peer: float(np.mean([r[peer]['success'] for r in both]))}
    if 'open3d_fpfh_ransac' in paired:
        p = paired['open3d_fpfh_ransac']
        goals.append(goal(f'{best}_success_rate_minus_open3d_fpfh_ransac_same_trials', 0.0, '>',
                          p[best] - p['open3d_fpfh_ransac']))
    if node is not None:
        node['summary'] = node_summary(node)
        goals += [
            goal('node_published_poses_over_5mm_add_s', 0, '==',
                 node['summary']['published_over_5mm_add_s']),
            goal('node_success_rate_within_2mm_2deg_symmetry_aware', 0.99, '>=',
                 node['summary']['success_rate']),
        ]
    write_report(args.out, goals, summary=summary, success_rate_per_object=per_object,
                 node_path=node,
                 paired_success_on_the_peers_trials=paired,
                 timing_exclusive_lock=timing, trials=len(records),
                 tolerance={'translation_m': TOL_T, 'rotation_deg': float(np.degrees(TOL_R))},
                 load_average_at_write=list(os.getloadavg()),
                 final_check=bool(getattr(args, 'final_check', False)),
                 accuracy_run_note=(
                     f"the summary's time_s figures are this run's, at a 1-min load average of "
                     f"{summary[best]['load_1min']['median']:.1f} (median over its trials); "
                     'timing_exclusive_lock, when present, holds trials re-timed by '
                     '--timing-only and the time goals use them'),
                 records=records,
                 stereo="block_matching over each scene's disparity band (min_disparity, "
                 'count): ' + str(SCENE_DISPARITY_BANDS) + ' (the demo stereo node settings, '
                 'stereo_manip_bringup.demo.SCENE_DISPARITY_BANDS), full resolution')


def timing_only(args, trials, models):
    path = results_dir() / f'{args.out}.json'
    data = json.loads(path.read_text())
    rng = np.random.default_rng(0)
    pick = rng.choice(len(trials), size=min(args.timing_only, len(trials)), replace=False)
    timing = dict(data.get('timing_exclusive_lock') or {})
    timing['load_average_before'] = list(os.getloadavg())
    for method in [m for m in args.methods if m in data['summary']]:
        _, _, _, name, pts, camera, _ = trials[pick[0]]
        run_method(method, models[name], pts, camera, 0)       # warm-up (numba cache load)
        times, cpu = [], []
        for i in pick:
            _, _, _, name, pts, camera, _ = trials[i]
            c0 = time.process_time()
            times.append(run_method(method, models[name], pts, camera, int(i),
                                    args.final_check)[1])
            cpu.append(time.process_time() - c0)
        # CPU time of the process (all its threads: numba voting runs on both cores)
        timing[method] = stats(times) | {'n': len(times), 'cpu_s': stats(cpu)}
        print(method, timing[method], flush=True)
    timing['load_average_after'] = list(os.getloadavg())
    timing['note'] = ('re-timed on a random subset of the same trials (numba kernels compiled '
                      'before timing), under the exclusive CPU lock (flock -x '
                      '/work/coord/cpu.lock) when the machine has one; see the load averages')

    class A:
        pass
    a = A()
    a.out, a.methods, a.final_check = args.out, list(data['summary']), args.final_check
    write(a, data['records'], data['summary'], data['success_rate_per_object'], timing,
          data.get('node_path'))


if __name__ == '__main__':
    main()
