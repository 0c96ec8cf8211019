"""
Benchmark: wrong poses and losses of object_localizer_node in the live graph, against truth.

Graph (separate processes from the install tree, as ``make demo`` starts them):
``synthetic_camera`` -> ``stereo_depth_node`` (census block matching, 160 disparities) ->
``object_localizer_node`` on the demo scenes ``peg_in_hole`` (peg; hole_block declared static;
NO initial pose: global acquisition from scratch) and ``revolute_pair`` (link_base, link_arm:
two identical bricks, which no geometric search can tell apart, so they get the objects' poses
at frame 0 as hints, as the demo does; in free-running mode the localizer starts later in the
scene, so the hints are stale and are verified, not trusted) and ``primitives`` (cube and
torus, hinted as the demo does), each

- free-running: the camera at ``--rate`` Hz with ``frame_step`` 3 (the scene at 10 fps), for
  ``--seconds``; the scene wraps around at its end (the objects jump back: a real loss);
- triggered: one frame per trigger (the demo's mode), the next after the localizer's status
  for that frame (or 20 s), ``--frames`` frames.

Every published pose is scored by ADD-S against the camera's truth topic of the same stamp.
Every loss (a TrackStatus with state LOST, or the reason of a re-acquisition in the same cloud)
is costed to the next verified pose: the object's own CPU time (the ``cpu_time`` of each of its
TrackStatus messages, from the loss to the verified pose, both included: the goal's figure), and
as an upper bound the localizer process's CPU time (/proc/<pid>/stat, sampled when each status
arrives; it also counts the other objects' tracking and searches of those clouds, e.g. both
bricks searched after the scene's loop jump, and message handling). A loss still open at the
end is unrecovered when the run went on for ``CENSOR_S`` (3 s of cloud stamps) after it;
later ones are censored (reported, not counted as failures: the run ended before a re-
acquisition could be expected). No peer runs here (the peer of the tracking stage is in
bench/localizer_tracking.py): this run counts wrong published poses, which must be zero.
Writes bench/results/localizer_live.json.
"""

import argparse
import os
import time

import numpy as np

from object_localizer.evaluation import add_s
from object_localizer.localization import prepare_model
from stereo_manip_tools.bench_report import goal, write_report
from stereo_manip_tools.conversions import pose_to_matrix, stamp_to_ns
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.processes import ExecutableProcess, make_node, process_cpu_seconds, \
    shutdown_node, spin_until, wait_for_settled_graph

#: a loss this close [s of cloud stamps] to the object's last status is censored, not a failure
CENSOR_S = 3.0

SCENES = {'peg_in_hole': (['hole_block', 'peg'], ['hole_block'], False),
          'revolute_pair': (['link_base', 'link_arm'], [], True),
          'primitives': (['cube', 'torus'], [], True)}


def _hints(scene, names):
    from stereo_depth.synthetic import make_scene
    from stereo_manip_tools.transforms import quaternion_from_matrix
    poses = make_scene(scene).poses(0)
    out = []
    for n in names:
        out += [float(v) for v in poses[n][:3, 3]] + \
            [float(v) for v in quaternion_from_matrix(poses[n][:3, :3])]
    return out


def _args(params, remap=None):
    out = []
    for k, v in params.items():
        if isinstance(v, bool):
            v = 'true' if v else 'false'
        elif isinstance(v, list):
            v = '[' + ','.join(str(x) for x in v) + ']'
        out += ['-p', f'{k}:={v}']
    for a, b in (remap or {}).items():
        out += ['-r', f'{a}:={b}']
    return out


def run(scene, mode, rate, seconds, frames, log, localizer_params=None):
    from geometry_msgs.msg import PoseStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Empty
    from stereo_manip_msgs.msg import TrackStatus

    names, static, hinted = SCENES[scene]
    cam = {'scene': scene, 'frame_step': 3, 'publish_depth': False, 'publish_disparity': False}
    cam.update({'trigger': True} if mode == 'triggered' else {'rate': rate})
    specs = [('stereo_depth', 'synthetic_camera', _args(cam, {'trigger': '/camera_trigger'})),
             ('stereo_depth', 'stereo_depth_node',
              _args({'method': 'block_matching', 'max_disparity': 160,
                     'input_qos': 'reliable'})),
             ('object_localizer', 'object_localizer_node',
              _args({'models': names, **({'static_objects': static} if static else {}),
                     **({'initial_poses': _hints(scene, names)} if hinted else {}),
                     **(localizer_params or {})}))]
    node = make_node(f'bench_live_{scene}')
    qos = QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE)
    poses = {n: [] for n in names}
    truth = {n: {} for n in names}
    statuses = {n: [] for n in names}
    procs = []
    for n in names:
        node.create_subscription(PoseStamped, f'/objects/{n}/pose',
                                 lambda m, n=n: poses[n].append(m), qos)
        node.create_subscription(PoseStamped, f'/objects/{n}/pose_truth',
                                 lambda m, n=n: truth[n].__setitem__(
                                     stamp_to_ns(m.header.stamp), pose_to_matrix(m.pose)), qos)
    trigger = node.create_publisher(Empty, '/camera_trigger', 10)
    try:
        for pkg, exe, ros_args in specs:
            procs.append(ExecutableProcess(pkg, exe, (), ros_args))
        localizer = procs[-1]
        for n in names:
            node.create_subscription(
                TrackStatus, f'/objects/{n}/status',
                lambda m, n=n: statuses[n].append(
                    (m, process_cpu_seconds(localizer.process.pid))), qos)
        for p, w in zip(procs, ('synthetic_camera', 'stereo_depth_node', 'object_localizer')):
            assert p.wait_for_node(node, w, 120), p.output()[-3000:]
        t0 = time.monotonic()
        if mode == 'triggered':
            spin_until(node, lambda: trigger.get_subscription_count() > 0, 30)
            wait_for_settled_graph(node, ['synthetic_camera', 'stereo_depth_node',
                                          'object_localizer'])
            for k in range(frames):
                n0 = len(statuses[names[-1]])
                trigger.publish(Empty())
                spin_until(node, lambda: len(statuses[names[-1]]) > n0, 60 if k == 0 else 20)
        else:
            spin_until(node, lambda: False, seconds)
        spin_until(node, lambda: False, 2.0)
        wall = time.monotonic() - t0
        dead = [exe for (pkg, exe, _), p in zip(specs, procs) if not p.running()]
    finally:
        tails = {}
        for (pkg, exe, _), p in zip(reversed(specs), reversed(procs)):
            p.stop()
            tails[exe] = p.output()[-1500:]
        shutdown_node(node)
    out = {'scene': scene, 'mode': mode, 'wall_s': wall, 'hints': hinted, 'dead_nodes': dead,
           'objects': {},
           'localizer_log_tail': tails.get('object_localizer_node', '')}
    for n in names:
        pts = prepare_model(load_obj(find_model(n))).points
        errs, unscored, wrong = [], 0, []
        status_at = {stamp_to_ns(m.header.stamp): m for m, _ in statuses[n]}
        first_ns = min(truth[n]) if truth[n] else 0
        for m in poses[n]:
            ns = stamp_to_ns(m.header.stamp)
            T = truth[n].get(ns)
            if T is None:
                unscored += 1
                continue
            errs.append(add_s(pose_to_matrix(m.pose), T, pts))
            if errs[-1] > 0.005:
                # every wrong pose with the status of its cloud, so its cause can be read here
                st = status_at.get(ns)
                P = pose_to_matrix(m.pose)
                wrong.append({
                    'stamp_s_after_first_truth': (ns - first_ns) * 1e-9,
                    'add_s_mm': errs[-1] * 1e3,
                    'translation_error_mm': float(np.linalg.norm(P[:3, 3] - T[:3, 3]) * 1e3),
                    'truth_xyz_m': T[:3, 3].tolist(), 'published_xyz_m': P[:3, 3].tolist(),
                    'status': None if st is None else {
                        'state': int(st.state), 'quality': float(st.quality),
                        'inlier_fraction': float(st.inlier_fraction),
                        'visible_residual_m': float(st.visible_residual),
                        'prediction_error_m': float(st.prediction_error),
                        'reason': st.reason}})
        # Losses: a LOST status, or a re-acquisition in the cloud where the track was lost.
        # Recovery CPU: the object's own (sum of its statuses' cpu_time from the loss to the
        # next verified pose, both included), and the localizer process's CPU from the status
        # before the loss to that pose (an upper bound: it includes the other objects).
        losses, recoveries, process_recoveries = [], [], []
        lost_from = None
        own = 0.0
        lost_ns = None
        states = []
        prev_cpu = None
        for m, cpu in statuses[n]:
            states.append(int(m.state))
            verified = m.state in (1, 3) and 'held' not in m.reason
            if 'track lost' in m.reason or 'failed its re-check' in m.reason:
                losses.append(cpu)
                if lost_from is None:
                    lost_from = prev_cpu if prev_cpu is not None else cpu
                    lost_ns = stamp_to_ns(m.header.stamp)
                    own = 0.0
            if lost_from is not None:
                own += m.cpu_time
            if verified and lost_from is not None:
                recoveries.append(own)
                process_recoveries.append(cpu - lost_from)
                lost_from = None
            prev_cpu = cpu
        open_s = None if lost_from is None else \
            (stamp_to_ns(statuses[n][-1][0].header.stamp) - lost_ns) * 1e-9
        e = np.array(errs) if errs else np.array([np.nan])
        out['objects'][n] = {
            'published': len(poses[n]), 'scored': len(errs), 'unscored': unscored,
            'statuses': len(statuses[n]),
            'add_s_mm': {'median': float(np.nanmedian(e) * 1e3),
                         'p95': float(np.nanpercentile(e, 95) * 1e3),
                         'max': float(np.nanmax(e) * 1e3)},
            'published_over_5mm': int(np.sum(e > 0.005)), 'wrong_poses': wrong,
            'losses': len(losses), 'recoveries': len(recoveries),
            'unrecovered_at_end': int(open_s is not None and open_s >= CENSOR_S),
            'censored_at_end': int(open_s is not None and open_s < CENSOR_S),
            'open_loss_s_before_end': open_s,
            'recovery_cpu_s': [float(x) for x in recoveries],
            'recovery_process_cpu_s': [float(x) for x in process_recoveries],
            'state_counts': {s: states.count(k) for k, s in enumerate(
                ('ACQUIRING', 'TRACKING', 'LOST', 'STATIC'))},
        }
        log(f'  {scene}/{mode} {n}: {out["objects"][n]}')
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    parser.add_argument('--rate', type=float, default=10.0, help='free-running camera rate')
    parser.add_argument('--seconds', type=float, default=45.0, help='free-running duration')
    parser.add_argument('--frames', type=int, default=40, help='triggered frames')
    parser.add_argument('--scenes', default='peg_in_hole,revolute_pair,primitives')
    parser.add_argument('--modes', default='free_running,triggered')
    parser.add_argument('--param', action='append', default=[], metavar='NAME=VALUE',
                        help='a localizer parameter (repeatable; an A/B of one setting)')
    parser.add_argument('--out', default='localizer_live',
                        help='result name (bench/results/<out>.json)')
    parser.add_argument('--rescore', action='store_true',
                        help='recompute the goals from the runs in the existing JSON')
    args = parser.parse_args()
    if args.rescore:
        import json
        from stereo_manip_tools.bench_report import results_dir
        old = json.loads((results_dir() / 'localizer_live.json').read_text())
        summarise(old['runs'], old['load_before'], old['args'])
        return
    runs = []
    load_before = os.getloadavg()
    for scene in args.scenes.split(','):
        for mode in args.modes.split(','):
            print(f'{scene} {mode} ...', flush=True)
            runs.append(run(scene, mode, args.rate, args.seconds, args.frames, print,
                            dict(p.split('=', 1) for p in args.param)))
    summarise(runs, load_before, vars(args))


def summarise(runs, load_before, args):
    """Goals from the runs; a loss never re-acquired leaves the CPU goal unmeasured (NaN)."""
    from localizer_graph_cpu import spread     # median / p95 / max / n (NaN when empty)
    objs = [o for r in runs for o in r['objects'].values()]
    over = sum(o['published_over_5mm'] for o in objs)
    recov = [x for o in objs for x in o['recovery_cpu_s']]
    process = [x for o in objs for x in o.get('recovery_process_cpu_s', [])]
    losses = sum(o['losses'] for o in objs)
    unrecovered = sum(o['unrecovered_at_end'] for o in objs)
    censored = sum(o.get('censored_at_end', 0) for o in objs)
    published = sum(o['scored'] for o in objs)
    goals = [
        goal('published_poses_over_5mm_add_s', 0, '==', over),
        goal('losses_not_reacquired', 0, '==', unrecovered),
        goal('reacquisition_cpu_s_max', 1.0, '<=',
             max(recov) if recov and not unrecovered else (float('nan') if losses else 0.0)),
        goal('scored_published_poses', 1, '>=', published),
        # a run in which an object never gets a pose is a loss the pose statistics cannot show
        goal('objects_without_any_pose_in_a_run', 0, '==',
             sum(o['published'] == 0 for o in objs)),
        goal('nodes_died', 0, '==', sum(len(r['dead_nodes']) for r in runs)),
    ]
    write_report(args.get('out', 'localizer_live'), goals, runs=runs, losses=losses,
                 unrecovered_at_end=unrecovered, censored_at_end=censored,
                 recovery_cpu_s=spread(recov),
                 recovery_process_cpu_s_upper_bound=spread(process),
                 load_before=load_before, load_after=os.getloadavg(), args=args)


if __name__ == '__main__':
    main()
