"""``demo``: the stereo_manip pipeline on the built-in synthetic scenes, scored against truth.

Every stage is a live ROS graph of separate processes (what ``ros2 launch
stereo_manip_bringup pipeline.launch.py`` starts on a ROS install), fed by the synthetic stereo
camera, whose exact ground truth scores each stage:

1. ``peg_in_hole``: synthetic_camera -> stereo_depth_node -> object_localizer_node (peg,
   hole_block) -> contact_correction_node. Scores: the peg's localisation error (ADD-S) before
   and after contact correction, penetration before and after, contact ranks seen.
2. ``revolute_pair``: synthetic_camera -> stereo_depth_node -> object_localizer_node (link_base,
   link_arm) -> joint_estimator_node. Scores: joint type, axis direction error and axis-line
   distance in the camera frame (invariant to the boxes' symmetries).
3. ``primitives``: synthetic_camera -> stereo_depth_node -> object_localizer_node (cube, torus)
   -> one ip_modeler_node per object on its segmented cloud. Scores: selected degree, RMS
   distance of the object's points to the zero set.

Writes ``<out>/report.json``, ``<out>/report.md``, one figure per stage and every node's log;
exits non-zero if a stage produced no result. Usage::

    scripts/ros2run stereo_manip_bringup demo --out demo_output [--frames 0.5]
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import sys
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['NodeSpec', 'Stage', 'run_stage', 'STAGES', 'main']


@dataclass
class NodeSpec:
    """One executable of the graph: package, executable, node name, parameters, remappings."""

    package: str
    executable: str
    node_name: str
    parameters: Dict[str, Any] = field(default_factory=dict)
    remappings: Dict[str, str] = field(default_factory=dict)

    def ros_args(self) -> List[str]:
        """``--ros-args`` list: node name, ``-p name:=value`` and ``-r from:=to``."""
        args = ['-r', f'__node:={self.node_name}']
        for k, v in self.parameters.items():
            args += ['-p', f'{k}:={_param_text(v)}']
        for a, b in self.remappings.items():
            args += ['-r', f'{a}:={b}']
        return args


def _param_text(value: Any) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ','.join(_param_text(v) for v in value) + ']'
    return str(value)


@dataclass
class Stage:
    """A demo stage: the graph to start, the topics to record, and how to score them."""

    name: str
    nodes: List[NodeSpec]
    topics: Dict[str, str]          # topic -> message type name (pkg/msg/Name)
    score: Callable[[Dict[str, List[Tuple[int, Any]]], 'Stage'], Dict[str, Any]]
    description: str = ''
    frames: int = 30                 # frames the camera is triggered for
    stamp_topic: str = ''            # a camera truth topic: gives each frame's stamp
    done_topics: Tuple[str, ...] = ()  # the graph's last outputs for a frame


def _camera(scene: str, frame_step: int = 1) -> NodeSpec:
    """The synthetic camera in software-trigger mode: one frame per trigger, so every frame
    passes through the whole graph however slow this machine is."""
    return NodeSpec('stereo_depth', 'synthetic_camera', 'synthetic_camera',
                    {'scene': scene, 'trigger': True, 'frame_step': frame_step,
                     'publish_depth': False, 'publish_disparity': False},
                    {'trigger': '/camera_trigger'})


# Disparity band of each scene's objects and table (600 px / 0.10 m camera), measured on the
# rendered truth over every 18th-25th frame of a loop: peg_in_hole 56-153 px, revolute_pair
# 58-162 px, primitives 59-120 px; each band below covers it with a margin of >= 5 px.
SCENE_DISPARITY_BANDS: Dict[str, Tuple[int, int]] = {
    'peg_in_hole': (48, 112),      # (min_disparity, max_disparity = count): 48..159 px
    'revolute_pair': (48, 120),    # 48..167 px
    'primitives': (48, 80),        # 48..127 px
}


def _stereo(scene: str) -> NodeSpec:
    """The stereo node searching only the scene's disparity band, publishing a cloud of every
    2nd pixel in both directions (a quarter of the points: the localiser voxelises at 3 mm,
    coarser than the 2-pixel spacing of ~1.5 mm at 0.45 m)."""
    dmin, count = SCENE_DISPARITY_BANDS[scene]
    return NodeSpec('stereo_depth', 'stereo_depth_node', 'stereo_depth_node',
                    {'method': 'block_matching', 'min_disparity': dmin, 'max_disparity': count,
                     'point_decimation': 2, 'input_qos': 'reliable'})


def _localizer(scene: str, models: Sequence[str]) -> NodeSpec:
    """The localiser, started from the objects' poses at the scene's first frame (the track is
    initialised once, as a robot would from its task set-up; afterwards it is pure tracking)."""
    from stereo_depth.synthetic import make_scene
    from stereo_manip_tools.transforms import quaternion_from_matrix
    poses = make_scene(scene).poses(0)
    initial: List[float] = []
    for name in models:
        T = poses[name]
        initial += [float(v) for v in T[:3, 3]] + [float(v) for v in quaternion_from_matrix(
            T[:3, :3])]
    return NodeSpec('object_localizer', 'object_localizer_node', 'object_localizer',
                    {'models': list(models), 'initial_poses': initial})


# --- scoring --------------------------------------------------------------------------------

def _by_stamp(records: List[Tuple[int, Any]]) -> Dict[int, Any]:
    return {stamp: msg for stamp, msg in records}


def _pose(msg: Any) -> np.ndarray:
    from stereo_manip_tools.conversions import pose_to_matrix
    return pose_to_matrix(msg.pose)


def _model_points(name: str) -> np.ndarray:
    from object_localizer.localization import prepare_model
    from stereo_manip_tools.mesh_io import find_model, load_obj
    return prepare_model(load_obj(find_model(name))).points


def score_peg_in_hole(data: Dict[str, List[Tuple[int, Any]]], stage: Stage) -> Dict[str, Any]:
    """ADD-S of the localised and corrected peg against truth, in the camera frame and relative
    to the hole block (what contact correction acts on), and contact figures per frame."""
    from object_localizer.evaluation import add_s
    from stereo_manip_tools.transforms import invert_transform
    truth = _by_stamp(data['/objects/peg/pose_truth'])
    observed = _by_stamp(data['/objects/peg/pose'])
    corrected = _by_stamp(data['/objects/peg/pose_corrected'])
    block_truth = _by_stamp(data['/objects/hole_block/pose_truth'])
    block = _by_stamp(data['/objects/hole_block/pose'])
    states = _by_stamp(data['/contact_state'])
    pts = _model_points('peg')
    rows = []
    for stamp in sorted(set(truth) & set(observed) & set(corrected) & set(states) & set(block)
                        & set(block_truth)):
        T = _pose(truth[stamp])
        rel_true = invert_transform(_pose(block_truth[stamp])) @ T
        to_block = invert_transform(_pose(block[stamp]))
        st = states[stamp]
        rows.append({
            'stamp_ns': stamp,
            'add_s_observed_m': add_s(_pose(observed[stamp]), T, pts),
            'add_s_corrected_m': add_s(_pose(corrected[stamp]), T, pts),
            'relative_add_s_observed_m': add_s(to_block @ _pose(observed[stamp]), rel_true, pts),
            'relative_add_s_corrected_m': add_s(to_block @ _pose(corrected[stamp]), rel_true,
                                                pts),
            'corrected': bool(st.corrected), 'rotation_rank': int(st.rotation_rank),
            'pairs': len(st.pairs), 'penetration_observed_m': float(st.penetration_depth),
            'contact_residual_after_m': float(st.max_contact_residual),
            'status': st.status,
        })
    out: Dict[str, Any] = {'frames_scored': len(rows), 'frames': rows,
                           'camera_frames': len(truth), 'localised_frames': len(observed)}
    if rows:
        obs = np.array([r['add_s_observed_m'] for r in rows])
        cor = np.array([r['add_s_corrected_m'] for r in rows])
        in_contact = np.array([r['corrected'] for r in rows])
        rel_obs = np.array([r['relative_add_s_observed_m'] for r in rows])[in_contact]
        rel_cor = np.array([r['relative_add_s_corrected_m'] for r in rows])[in_contact]
        out.update(
            median_add_s_observed_mm=float(np.median(obs) * 1000),
            median_add_s_corrected_mm=float(np.median(cor) * 1000),
            median_relative_add_s_observed_mm=float(np.median(rel_obs) * 1000)
            if len(rel_obs) else float('nan'),
            median_relative_add_s_corrected_mm=float(np.median(rel_cor) * 1000)
            if len(rel_cor) else float('nan'),
            frames_corrected=int(in_contact.sum()),
            max_penetration_observed_mm=float(max(r['penetration_observed_m']
                                                  for r in rows) * 1000),
            max_contact_residual_after_mm=float(max(
                (r['contact_residual_after_m'] for r in rows if r['corrected']),
                default=0.0) * 1000),
            rotation_ranks_seen=sorted({r['rotation_rank'] for r in rows if r['corrected']}))
    return out


def _line_errors(axis_est: np.ndarray, point_est: np.ndarray, axis_true: np.ndarray,
                 point_true: np.ndarray) -> Tuple[float, float]:
    """Angle [deg] between two lines and distance [m] of the true point from the estimated line.
    """
    a = axis_est / np.linalg.norm(axis_est)
    b = axis_true / np.linalg.norm(axis_true)
    angle = float(np.degrees(np.arccos(np.clip(abs(a @ b), 0.0, 1.0))))
    d = point_true - point_est
    return angle, float(np.linalg.norm(d - (d @ a) * a))


def score_revolute_pair(data: Dict[str, List[Tuple[int, Any]]], stage: Stage) -> Dict[str, Any]:
    """Joint type and axis line of the newest estimate vs the scene's true joint."""
    from stereo_depth.synthetic import make_scene
    from stereo_manip_tools.conversions import point_to_numpy, stamp_to_ns, vector3_to_numpy
    estimates = data['/joint_estimate']
    base_obs = _by_stamp(data['/objects/link_base/pose'])
    base_true = _by_stamp(data['/objects/link_base/pose_truth'])
    truth = make_scene('revolute_pair').extras(0)['joint']
    out: Dict[str, Any] = {'estimates': len(estimates), 'camera_frames': len(base_true),
                           'localised_frames': len(base_obs)}
    names = {0: 'fixed', 1: 'revolute', 2: 'prismatic', 3: 'spherical', 4: 'cylindrical',
             5: 'planar'}
    history = []
    for _, est in estimates:
        stamp = stamp_to_ns(est.header.stamp)
        if stamp not in base_obs or stamp not in base_true:
            continue
        Tb_obs, Tb_true = _pose(base_obs[stamp]), _pose(base_true[stamp])
        axis_cam = Tb_obs[:3, :3] @ vector3_to_numpy(est.axis_in_b)
        point_cam = Tb_obs[:3, :3] @ point_to_numpy(est.point_in_b) + Tb_obs[:3, 3]
        axis_true = Tb_true[:3, :3] @ np.asarray(truth['axis_base'], float)
        point_true = Tb_true[:3, :3] @ np.asarray(truth['point_base'], float) + Tb_true[:3, 3]
        angle, dist = _line_errors(axis_cam, point_cam, axis_true, point_true)
        history.append({'stamp_ns': stamp, 'type': names.get(est.joint_type, '?'),
                        'samples': int(est.sample_count), 'outliers': int(est.outlier_count),
                        'axis_error_deg': angle, 'axis_line_distance_m': dist,
                        'status': est.status})
    out['history'] = history
    if history:
        last = history[-1]
        out.update(final_type=last['type'], final_axis_error_deg=last['axis_error_deg'],
                   final_axis_line_distance_mm=last['axis_line_distance_m'] * 1000,
                   final_samples=last['samples'], true_type=truth['type'])
    return out


def score_primitives(data: Dict[str, List[Tuple[int, Any]]], stage: Stage) -> Dict[str, Any]:
    """Degree and RMS distance of each object's newest implicit polynomial."""
    out: Dict[str, Any] = {}
    for name in ('cube', 'torus'):
        fits = data[f'/objects/{name}/implicit_polynomial']
        if not fits:
            out[name] = {'fits': 0}
            continue
        last = fits[-1][1]
        out[name] = {'fits': len(fits), 'degree': int(last.degree),
                     'rms_distance_mm': float(last.rms_distance) * 1000,
                     'max_distance_mm': float(last.max_distance) * 1000,
                     'points': int(last.point_count), 'status': last.status}
    return {'objects': out}


STAGES: Dict[str, Callable[[], Stage]] = {
    'peg_in_hole': lambda: Stage(
        'peg_in_hole',
        [_camera('peg_in_hole', 3), _stereo('peg_in_hole'),
         _localizer('peg_in_hole', ['peg', 'hole_block']),
         NodeSpec('contact_correction', 'contact_correction_node', 'contact_correction',
                  {'moving_object': 'peg', 'fixed_object': 'hole_block'},
                  {'moving_pose': '/objects/peg/pose', 'fixed_pose': '/objects/hole_block/pose',
                   'corrected_pose': '/objects/peg/pose_corrected'})],
        {'/objects/peg/pose_truth': 'geometry_msgs/msg/PoseStamped',
         '/objects/peg/pose': 'geometry_msgs/msg/PoseStamped',
         '/objects/hole_block/pose_truth': 'geometry_msgs/msg/PoseStamped',
         '/objects/hole_block/pose': 'geometry_msgs/msg/PoseStamped',
         '/objects/peg/pose_corrected': 'geometry_msgs/msg/PoseStamped',
         '/contact_state': 'stereo_manip_msgs/msg/ContactState'},
        score_peg_in_hole, 'contact correction of a localised peg (Section 3)',
        frames=75, stamp_topic='/objects/peg/pose_truth', done_topics=('/contact_state',)),
    'revolute_pair': lambda: Stage(
        'revolute_pair',
        [_camera('revolute_pair', 3), _stereo('revolute_pair'),
         _localizer('revolute_pair', ['link_base', 'link_arm']),
         NodeSpec('joint_estimator', 'joint_estimator_node', 'joint_estimator',
                  {'min_poses': 10, 'estimate_every': 2},
                  {'link_a_pose': '/objects/link_arm/pose',
                   'link_b_pose': '/objects/link_base/pose'})],
        {'/objects/link_base/pose_truth': 'geometry_msgs/msg/PoseStamped',
         '/objects/link_base/pose': 'geometry_msgs/msg/PoseStamped',
         '/objects/link_arm/pose': 'geometry_msgs/msg/PoseStamped',
         '/joint_estimate': 'stereo_manip_msgs/msg/JointEstimate'},
        score_revolute_pair, 'joint estimation from two localised links (Section 4)',
        frames=60, stamp_topic='/objects/link_base/pose_truth',
        done_topics=('/objects/link_arm/pose',)),
    'primitives': lambda: Stage(
        'primitives',
        [_camera('primitives', 3), _stereo('primitives'),
         _localizer('primitives', ['cube', 'torus'])] + [
            NodeSpec('ip_modeler', 'ip_modeler_node', f'ip_modeler_{n}',
                     {'input_qos': 'reliable'},
                     {'cloud': f'/objects/{n}/cloud',
                      'implicit_polynomial': f'/objects/{n}/implicit_polynomial',
                      'zero_set_marker': f'/objects/{n}/zero_set_marker'})
            for n in ('cube', 'torus')],
        {'/objects/cube/pose_truth': 'geometry_msgs/msg/PoseStamped',
         '/objects/cube/implicit_polynomial': 'stereo_manip_msgs/msg/ImplicitPolynomial',
         '/objects/torus/implicit_polynomial': 'stereo_manip_msgs/msg/ImplicitPolynomial'},
        score_primitives, 'implicit polynomials of segmented stereo clouds (Section 5)',
        frames=4, stamp_topic='/objects/cube/pose_truth',
        done_topics=('/objects/cube/implicit_polynomial',
                     '/objects/torus/implicit_polynomial')),
}


# --- running --------------------------------------------------------------------------------

def run_stage(stage: Stage, frame_timeout: float = 20.0,
              log: Callable[[str], None] = print
              ) -> Tuple[Dict[str, List[Tuple[int, Any]]], Dict[str, Any]]:
    """Start the stage's graph, trigger ``stage.frames`` camera frames one after another (the
    next when the graph's last output for the previous one arrived, or after
    ``frame_timeout`` s), record the stage's topics, stop the graph.

    :returns: ``({topic: [(stamp_ns, msg), ...]}, {'tails': {node: output}, 'frames_timed_out':
        n, 'seconds_per_frame': s})``.
    :raises RuntimeError: a node did not come up or died (its output is in the message).
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Empty

    from stereo_manip_tools.bag_io import get_message_class
    from stereo_manip_tools.conversions import stamp_to_ns
    from stereo_manip_tools.processes import ExecutableProcess, make_node, shutdown_node, \
        spin_until

    observer = make_node(f'demo_{stage.name}')
    data: Dict[str, List[Tuple[int, Any]]] = {t: [] for t in stage.topics}
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    for topic, type_name in stage.topics.items():
        def record(msg: Any, topic: str = topic) -> None:
            data[topic].append((stamp_to_ns(msg.header.stamp), msg))
        observer.create_subscription(get_message_class(type_name), topic, record, qos)
    trigger = observer.create_publisher(Empty, '/camera_trigger', 10)
    procs: List[Tuple[NodeSpec, ExecutableProcess]] = []
    info: Dict[str, Any] = {'tails': {}, 'logs': {}, 'frames_timed_out': 0}
    t_start = time.monotonic()
    try:
        for spec in stage.nodes:
            proc = ExecutableProcess(spec.package, spec.executable, (), spec.ros_args())
            procs.append((spec, proc))
        for spec, proc in procs:
            if not proc.wait_for_node(observer, spec.node_name, 120.0):
                raise RuntimeError(f'{spec.package}/{spec.executable} did not start:\n'
                                   + proc.output()[-3000:])
            log(f'  started {spec.package}/{spec.executable} as {spec.node_name}')
        spin_until(observer, lambda: trigger.get_subscription_count() > 0, 30.0)
        t_start = time.monotonic()
        for k in range(stage.frames):
            n_stamps = len(data[stage.stamp_topic])
            trigger.publish(Empty())
            if not spin_until(observer, lambda: len(data[stage.stamp_topic]) > n_stamps, 30.0):
                raise RuntimeError('the camera did not answer a trigger within 30 s')
            stamp = data[stage.stamp_topic][-1][0]
            done = spin_until(observer, lambda: all(
                any(s == stamp for s, _ in data[t][-5:]) for t in stage.done_topics),
                frame_timeout)
            info['frames_timed_out'] += not done
            if (k + 1) % 10 == 0 or k + 1 == stage.frames:
                log(f'  [{stage.name}] frame {k + 1}/{stage.frames}: '
                    + ', '.join(f'{t}: {len(v)}' for t, v in data.items()))
            dead = [s.node_name for s, p in procs if not p.running()]
            if dead:
                raise RuntimeError(f'node(s) exited early: {", ".join(dead)}\n' + '\n'.join(
                    p.output()[-2000:] for s, p in procs if s.node_name in dead))
        spin_until(observer, lambda: False, 1.0)  # late messages of the last frame
    finally:
        info['seconds_per_frame'] = (time.monotonic() - t_start) / max(stage.frames, 1)
        for spec, proc in reversed(procs):
            proc.stop()
            info['logs'][spec.node_name] = proc.output()
            info['tails'][spec.node_name] = info['logs'][spec.node_name][-1500:]
        shutdown_node(observer)
    return data, info


def _figure(stage: str, result: Dict[str, Any], path: Path) -> Optional[Path]:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    if stage == 'peg_in_hole' and result.get('frames'):
        rows = result['frames']
        t = (np.array([r['stamp_ns'] for r in rows]) - rows[0]['stamp_ns']) / 1e9
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.plot(t, [r['add_s_observed_m'] * 1000 for r in rows], 'o-', label='localised')
        ax.plot(t, [r['add_s_corrected_m'] * 1000 for r in rows], 's-',
                label='after contact correction')
        ax.set_xlabel('time [s]')
        ax.set_ylabel('peg ADD-S error [mm]')
        ax.legend()
        ax.set_title('peg_in_hole: pose error vs ground truth')
    elif stage == 'revolute_pair' and result.get('history'):
        h = result['history']
        t = (np.array([r['stamp_ns'] for r in h]) - h[0]['stamp_ns']) / 1e9
        fig, ax = plt.subplots(figsize=(7, 3.5))
        ax.plot(t, [r['axis_error_deg'] for r in h], 'o-', label='axis direction [deg]')
        ax.plot(t, [r['axis_line_distance_m'] * 1000 for r in h], 's-',
                label='axis line distance [mm]')
        ax.set_xlabel('time [s]')
        ax.legend()
        ax.set_title('revolute_pair: joint axis error vs ground truth')
    else:
        return None
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _summary_lines(name: str, result: Dict[str, Any]) -> List[str]:
    if name == 'peg_in_hole':
        if not result.get('frames_scored'):
            return ['no frame made it through the whole graph']
        return [f"frames scored: {result['frames_scored']} (camera {result['camera_frames']},"
                f" localised {result['localised_frames']}); contact-corrected: "
                f"{result['frames_corrected']}",
                f"peg ADD-S median (camera frame): localised "
                f"{result['median_add_s_observed_mm']:.2f} mm, after correction "
                f"{result['median_add_s_corrected_mm']:.2f} mm",
                f"peg relative to the localised hole block, frames in contact: ADD-S median "
                f"{result['median_relative_add_s_observed_mm']:.2f} mm localised, "
                f"{result['median_relative_add_s_corrected_mm']:.2f} mm after correction",
                f"max penetration observed {result['max_penetration_observed_mm']:.2f} mm; max "
                f"contact residual after correction {result['max_contact_residual_after_mm']:.4f}"
                f" mm; rotation ranks seen {result['rotation_ranks_seen']}"]
    if name == 'revolute_pair':
        if 'final_type' not in result:
            return [f"no joint estimate scored ({result['estimates']} estimates, "
                    f"{result['localised_frames']} localised frames)"]
        return [f"joint type: {result['final_type']} (true: {result['true_type']}), "
                f"{result['final_samples']} poses",
                f"axis direction error {result['final_axis_error_deg']:.2f} deg, axis line "
                f"distance {result['final_axis_line_distance_mm']:.2f} mm"]
    return [f"{obj}: " + (f"degree {r['degree']}, RMS distance {r['rms_distance_mm']:.2f} mm over "
                          f"{r['points']} points" if r.get('fits') else 'no fit')
            for obj, r in result['objects'].items()]


def _stage_ok(name: str, result: Dict[str, Any]) -> bool:
    if name == 'peg_in_hole':
        return result.get('frames_scored', 0) > 0
    if name == 'revolute_pair':
        return 'final_type' in result
    return all(r.get('fits', 0) > 0 for r in result['objects'].values())


def main(args: Optional[Sequence[str]] = None) -> int:
    """Run the demo stages; returns 0 when every stage produced a scored result."""
    parser = argparse.ArgumentParser(prog='demo', description=__doc__.split('\n\n')[0])
    parser.add_argument('--out', default='demo_output', help='report directory')
    parser.add_argument('--frames', type=float, default=1.0,
                        help='scale the number of frames of every stage (e.g. 0.5 for a '
                             'quicker run)')
    parser.add_argument('--frame-timeout', type=float, default=20.0,
                        help='seconds to wait for the graph to finish one frame')
    parser.add_argument('--stages', nargs='+', choices=list(STAGES), default=list(STAGES))
    opts = parser.parse_args(args)
    if not opts.frames > 0:
        parser.error('--frames must be > 0')
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    out = Path(opts.out)
    out.mkdir(parents=True, exist_ok=True)
    report: Dict[str, Any] = {'stages': {}}
    md = ['# stereo_manip demo report', '',
          'Synthetic scenes through a live graph of separate processes; the camera is '
          'software-triggered frame by frame; every figure is scored against the synthetic '
          'camera\'s exact ground truth.', '']
    ok = True
    for name in opts.stages:
        stage = STAGES[name]()
        stage.frames = max(1, int(round(stage.frames * opts.frames)))
        print(f'== stage {name}: {stage.description} ({stage.frames} frames)', flush=True)
        t0 = time.monotonic()
        try:
            data, info = run_stage(stage, opts.frame_timeout,
                                   log=lambda s: print(s, flush=True))
            result = stage.score(data, stage)
        except RuntimeError as exc:
            print(f'stage {name} failed: {exc}', file=sys.stderr, flush=True)
            result, info = {'error': str(exc)}, {'tails': {}}
        result['wall_time_s'] = time.monotonic() - t0
        for node, text in info.get('logs', {}).items():
            (out / f'{name}.{node}.log').write_text(text)
        result['frames_triggered'] = stage.frames
        result['frames_timed_out'] = info.get('frames_timed_out')
        result['seconds_per_frame'] = info.get('seconds_per_frame')
        stage_ok = 'error' not in result and _stage_ok(name, result)
        ok &= stage_ok
        report['stages'][name] = result
        fig = _figure(name, result, out / f'{name}.png') if stage_ok else None
        lines = _summary_lines(name, result) if 'error' not in result else [result['error']]
        if 'error' not in result:
            lines.append(f"{stage.frames} frames at {result['seconds_per_frame']:.2f} s per "
                         f"frame through the graph; {result['frames_timed_out']} timed out")
        md += [f'## {name}: {stage.description}', ''] + [f'- {line}' for line in lines]
        if fig:
            md += ['', f'![{name}]({fig.name})']
        md.append('')
        for line in lines:
            print(f'  {line}', flush=True)
        if not stage_ok:
            print(f'  stage {name} produced no scored result; node output tails:', flush=True)
            for node, tail in info['tails'].items():
                print(f'  --- {node}\n{tail}', flush=True)
    (out / 'report.json').write_text(json.dumps(report, indent=2, default=str) + '\n')
    (out / 'report.md').write_text('\n'.join(md) + '\n')
    print(f'report: {out / "report.md"}', flush=True)
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
