#!/usr/bin/env python3
"""
The live graphs at camera rate: rate, latency, drops and CPU per node, as separate processes.

Each run starts one demo graph (``stereo_manip_bringup.demo.STAGES``: the same nodes,
parameters and remappings ``make demo`` and the launch file use) with the synthetic camera
free-running at ``rate`` Hz, 640x480, and observes it from this process:

* every topic's rate and latency = receipt time - header stamp of the stereo pair it came from
  (the camera stamps a pair when it exists, i.e. after rendering; its render time is reported
  separately), median / p90 / p95 / max;
* drops: camera frames (stamps on ``left/camera_info``) whose stamp never appears on a topic;
  "before the contact node" = frames that reach neither the localiser's peg pose nor its peg
  status (a frame processed but not verified is not a drop: it is flagged);
* CPU per node from ``/proc/<pid>/stat`` (utime + stime over the window, % of one core), the
  observer's own CPU, and the load average.

The peer in the same run is the graph as main configured it (``scene:rate:peer``): full
disparity range 0-159 px, every pixel in the cloud, numba's default threading layer (OpenMP
here), OpenBLAS with one thread per core, the IP modeller's default point budget. Ours adds
``stereo_manip_bringup.demo.LIVE_PARAMETERS``: the stereo node's kernels on one thread, the IP
modellers fitting at most once per 2 s each and the joint estimator re-estimating every 30th
pose pair (with a free-running camera their output rates, ~0.5 Hz per object and 0.33 Hz, are
design figures; the inputs in between are skipped and counted, not dropped frames of the pose
path).

Usage::

    ROS_DOMAIN_ID=74 flock -x /work/coord/cpu.lock .venv/bin/python bench/pipeline_realtime.py
    python bench/pipeline_realtime.py --runs peg_in_hole:10 peg_in_hole:30 peg_in_hole:10:peer
    python bench/pipeline_realtime.py --update --runs revolute_pair:10 primitives:10 \
        primitives:10:peer

Writes ``bench/results/pipeline_realtime.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import struct
import sys
import time
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from stereo_manip_tools.bench_report import goal, results_dir, write_report
from stereo_manip_tools.processes import process_cpu_seconds

# What each scene's graph is judged on: the topic carrying its final output, and the topics
# whose arrival means "the frame reached the last node's input".
FINAL_TOPIC = {'peg_in_hole': '/objects/peg/pose_corrected',
               'revolute_pair': '/objects/link_arm/pose',
               'primitives': '/objects/cube/pose'}
REACHED_LAST_NODE = {'peg_in_hole': ('/objects/peg/pose', '/objects/peg/status'),
                     'revolute_pair': ('/objects/link_arm/pose', '/objects/link_arm/status'),
                     'primitives': ('/objects/cube/pose', '/objects/cube/status')}
OBJECTS = {'peg_in_hole': ('peg', 'hole_block'), 'revolute_pair': ('link_base', 'link_arm'),
           'primitives': ('cube', 'torus')}
EXTRA_TOPICS = {
    'peg_in_hole': {'/objects/peg/pose_corrected': 'geometry_msgs/msg/PoseStamped',
                    '/contact_state': 'stereo_manip_msgs/msg/ContactState'},
    'revolute_pair': {'/joint_estimate': 'stereo_manip_msgs/msg/JointEstimate'},
    'primitives': {'/objects/cube/implicit_polynomial':
                   'stereo_manip_msgs/msg/ImplicitPolynomial',
                   '/objects/torus/implicit_polynomial':
                   'stereo_manip_msgs/msg/ImplicitPolynomial'},
}


def cdr_stamp_ns(data: bytes) -> int:
    """
    Read the header stamp of a serialised message that starts with a ``std_msgs/Header``.

    Header stamp of a serialised (CDR, little or big endian) message that starts with a
    ``std_msgs/Header``: 4 bytes encapsulation, int32 sec, uint32 nanosec.
    """
    endian = '<' if data[1] == 1 else '>'
    sec, nsec = struct.unpack_from(endian + 'iI', data, 4)
    return sec * 1_000_000_000 + nsec


def percentiles(values: List[float]) -> Dict[str, float]:
    """median, p90, p95, max (NaN when empty)."""
    if not values:
        return {'median': float('nan'), 'p90': float('nan'), 'p95': float('nan'),
                'max': float('nan'), 'n': 0}
    a = np.asarray(values, float)
    return {'median': float(np.median(a)), 'p90': float(np.percentile(a, 90)),
            'p95': float(np.percentile(a, 95)), 'max': float(a.max()), 'n': int(len(a))}


def graph_specs(scene: str, rate: float, peer: bool) -> list:
    """
    Describe the demo graph of ``scene`` with the camera free-running at ``rate``.

    The demo graph of ``scene`` with the camera free-running at ``rate`` (``peer``: main's
    stereo configuration).
    """
    from stereo_manip_bringup.demo import LIVE_PARAMETERS, STAGES
    nodes = STAGES[scene]().nodes
    for spec in nodes:
        if spec.executable == 'synthetic_camera':
            # the scene at its own speed (30 fps nominal), played back and forth: motion
            # stays continuous (a looping scene teleports the peg back to its start)
            spec.parameters.update(trigger=False, rate=float(rate), playback='bounce',
                                   frame_step=max(1, int(round(30.0 / rate))))
            spec.remappings.pop('trigger', None)
        if spec.executable == 'stereo_depth_node' and peer:
            spec.parameters.update(min_disparity=0, max_disparity=160, point_decimation=1,
                                   numba_threading_layer='default')
        if not peer:      # the free-running settings (bounded rates, one stereo thread)
            spec.parameters.update(LIVE_PARAMETERS.get(spec.executable, {}))
        if peer:
            spec.env = {}
            if spec.executable == 'ip_modeler_node':
                spec.parameters = {'input_qos': 'reliable'}
    return nodes


def run_graph(scene: str, rate: float, seconds: float, peer: bool = False,
              warmup_timeout: float = 150.0, settle: float = 4.0) -> Dict[str, Any]:
    """Start the graph, wait for its first final output, observe ``seconds`` s, stop it."""
    from rclpy.qos import qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, PointCloud2

    from stereo_manip_tools.bag_io import get_message_class
    from stereo_manip_tools.conversions import stamp_to_ns
    from stereo_manip_tools.processes import ExecutableProcess, make_node, shutdown_node, \
        spin_until

    observer = make_node(f'bench_pipeline_{os.getpid()}')
    arrivals: Dict[str, List[Tuple[int, int]]] = {}    # topic -> [(stamp_ns, receipt_ns)]

    def recorder(topic: str, raw: bool = False):
        arrivals[topic] = []

        def record(msg: Any) -> None:
            now = time.time_ns()
            stamp = cdr_stamp_ns(msg) if raw else stamp_to_ns(msg.header.stamp)
            arrivals[topic].append((stamp, now))
        return record

    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    observer.create_subscription(CameraInfo, '/left/camera_info',
                                 recorder('/left/camera_info'), qos_profile_sensor_data)
    # the cloud as raw bytes: only its stamp is read, no deserialisation cost in the observer;
    # reliable (keep last 1), as the localiser reads it: best-effort DDS loses whole samples of
    # a megabyte cloud when one fragment is lost, which would count as drops of the graph
    observer.create_subscription(PointCloud2, '/points2', recorder('/points2', raw=True),
                                 QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE),
                                 raw=True)
    topics: Dict[str, str] = {}
    for name in OBJECTS[scene]:
        topics[f'/objects/{name}/pose'] = 'geometry_msgs/msg/PoseStamped'
        topics[f'/objects/{name}/status'] = 'stereo_manip_msgs/msg/TrackStatus'
    topics.update(EXTRA_TOPICS[scene])
    unavailable = []
    for topic, type_name in topics.items():
        try:
            cls = get_message_class(type_name)
        except Exception:  # noqa: BLE001 - e.g. TrackStatus before the localizer branch lands
            unavailable.append(topic)
            continue
        observer.create_subscription(cls, topic, recorder(topic), reliable)

    specs = graph_specs(scene, rate, peer)
    procs: List[Tuple[Any, Any]] = []
    out: Dict[str, Any] = {'scene': scene, 'camera_rate_hz': rate, 'peer': peer,
                           'unavailable_topics': unavailable,
                           'nodes': {s.node_name: {'package': s.package,
                                                   'executable': s.executable,
                                                   'parameters': s.parameters}
                                     for s in specs}}
    final = FINAL_TOPIC[scene]
    try:
        t_start = time.monotonic()
        # the camera last, once its readers are up (the demo does the same)
        for spec in sorted(specs, key=lambda n: n.executable == 'synthetic_camera'):
            proc = ExecutableProcess(spec.package, spec.executable, (), spec.ros_args(),
                                     env=spec.env)
            procs.append((spec, proc))
            if not proc.wait_for_node(observer, spec.node_name, 120.0):
                raise RuntimeError(f'{spec.executable} did not start:\n{proc.output()[-2000:]}')
            if spec.executable == 'stereo_depth_node':
                proc.wait_for_output('warm-up', 60.0)       # kernels loaded
        if not spin_until(observer, lambda: len(arrivals[final]) > 0
                          or any(not p.running() for _, p in procs), warmup_timeout):
            raise RuntimeError(f'no {final} within {warmup_timeout} s')
        dead = [s.node_name for s, p in procs if not p.running()]
        if dead:
            raise RuntimeError(f'node(s) died: {dead}\n' + '\n'.join(
                p.output()[-2000:] for s, p in procs if s.node_name in dead))
        out['startup_s'] = time.monotonic() - t_start
        spin_until(observer, lambda: False, settle)          # JIT/caches warm, queues empty
        cpu0 = {s.node_name: process_cpu_seconds(p.process.pid) for s, p in procs}
        own0 = time.process_time()
        load0 = os.getloadavg()
        w0_ns, w0 = time.time_ns(), time.monotonic()
        spin_until(observer, lambda: False, seconds)
        w1_ns, w1 = time.time_ns(), time.monotonic()
        cpu1 = {s.node_name: process_cpu_seconds(p.process.pid) for s, p in procs}
        own1 = time.process_time()
        load1 = os.getloadavg()
        spin_until(observer, lambda: False, 2.0)             # late outputs of the last frames
        window = w1 - w0
        out['window_s'] = window
        out['load_average_1min'] = {'start': load0[0], 'end': load1[0]}
        out['cpu_percent_of_one_core'] = {n: 100.0 * (cpu1[n] - cpu0[n]) / window
                                          for n in cpu0}
        out['cpu_percent_of_one_core']['observer (this benchmark)'] = \
            100.0 * (own1 - own0) / window
        out['logs_tail'] = {s.node_name: p.output()[-1500:] for s, p in procs}
        stereo_log = next((p.output() for s, p in procs
                           if s.executable == 'stereo_depth_node'), '')
        # the stereo node's own figure: wall time per processed pair, per stats period
        out['stereo_node_ms_per_frame_per_period'] = [
            float(m) for m in re.findall(r'Hz, ([0-9.]+) ms/frame\)', stereo_log)[1:]]
        out.update(analyse(arrivals, w0_ns, w1_ns, window, scene))
    finally:
        for spec, proc in reversed(procs):
            proc.stop()
        shutdown_node(observer)
    return out


def analyse(arrivals: Dict[str, List[Tuple[int, int]]], w0_ns: int, w1_ns: int,
            window: float, scene: str) -> Dict[str, Any]:
    """Per-topic rate, latency and drops of the frames the camera stamped inside the window."""
    camera = sorted({s for s, _ in arrivals['/left/camera_info'] if w0_ns <= s < w1_ns})
    cam_set = set(camera)
    gaps = np.diff(np.array(camera, float)) / 1e6 if len(camera) > 1 else np.array([])
    topics: Dict[str, Any] = {}
    for topic, rows in arrivals.items():
        inside = {}
        for stamp, recv in rows:
            if stamp in cam_set and stamp not in inside:
                inside[stamp] = recv
        lat = [(recv - stamp) / 1e6 for stamp, recv in inside.items()]
        topics[topic] = {
            'messages': len(inside),
            'rate_hz': len(inside) / window,
            'latency_ms': percentiles(lat),
            'frames_missing': len(camera) - len(inside),
            'frames_missing_fraction': (1.0 - len(inside) / len(camera)) if camera else 1.0,
        }
    reached = set()
    for topic in REACHED_LAST_NODE[scene]:
        reached |= {s for s, _ in arrivals.get(topic, []) if s in cam_set}
    final = FINAL_TOPIC[scene]
    return {
        'camera_frames': len(camera),
        'camera_rate_measured_hz': len(camera) / window,
        'camera_interval_ms': percentiles(list(gaps)),
        'topics': topics,
        'frames_reaching_last_node': len(reached),
        'dropped_before_last_node_fraction': (1.0 - len(reached) / len(camera))
        if camera else 1.0,
        'final_topic': final,
        'final_rate_hz': topics[final]['rate_hz'],
        'final_latency_ms': topics[final]['latency_ms'],
    }


RATE_TARGET_HZ = 9.9    # 10 Hz less 1 % for the camera timer's own rate (9.998 Hz measured)

NOTES = ['rate targets are 9.9 Hz: the camera timer set to 10 Hz delivers 9.998 Hz; the '
         'delivered-frames goal (100 %) holds the real requirement',
         'latency = receipt time in this observer - header stamp of the stereo pair (stamped '
         'by the camera after rendering)',
         'drops before the contact node: camera frames with neither a peg pose nor a peg status '
         'from the localiser',
         'cpu_ms_per_output_frame: CPU of the node over the window / its output messages',
         'cpu_ms_per_camera_frame: CPU of each node over the window / camera frames in it, and '
         'the sum over the nodes: the graph fits 2 cores at the camera rate when the sum is '
         'well below 2 x the frame interval (load-independent, unlike the rates)']

# node -> the topic whose messages count its processed frames
_OUTPUT_OF = {'stereo_depth_node': '/points2'}


def cpu_per_frame(run: Dict[str, Any]) -> Dict[str, float]:
    """
    CPU [ms] per frame a node put out (a load-independent cost).

    The stereo node per cloud, the localiser per status of its first object.
    """
    out = {}
    first_object = next((t for t in run['topics'] if t.endswith('/status')), None)
    for node, pct in run['cpu_percent_of_one_core'].items():
        topic = _OUTPUT_OF.get(node, first_object if node == 'object_localizer' else None)
        n = run['topics'].get(topic, {}).get('messages', 0) if topic else 0
        if n:
            out[node] = pct / 100.0 * run['window_s'] * 1000.0 / n
    return out


def cpu_per_camera_frame(run: Dict[str, Any]) -> Dict[str, float]:
    """
    Return the CPU [ms] of every node per camera frame, and their sum.

    CPU [ms] of every node per camera frame of the window, and their sum (the graph's
    work per frame: below 2 x the frame interval it fits on 2 cores, whatever the load).
    """
    n = run.get('camera_frames', 0)
    if not n:
        return {}
    out = {node: pct / 100.0 * run['window_s'] * 1000.0 / n
           for node, pct in run['cpu_percent_of_one_core'].items()}
    out['all nodes (observer excluded)'] = sum(v for k, v in out.items()
                                               if not k.startswith('observer'))
    return out


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--runs', nargs='*',
                        default=['peg_in_hole:10', 'peg_in_hole:30', 'peg_in_hole:10:peer',
                                 'revolute_pair:10', 'primitives:10', 'primitives:10:peer'],
                        help='scene:rate[:peer] runs, in order')
    parser.add_argument('--seconds', type=float, default=30.0, help='observation window [s]')
    parser.add_argument('--bound-ms', type=float, default=250.0,
                        help='latency bound claimed at 30 Hz (p95 and max of the final output)')
    parser.add_argument('--out-name', default='pipeline_realtime')
    parser.add_argument('--note', default='',
                        help='a line for the notes (e.g. how the CPU lock was held)')
    parser.add_argument('--update', action='store_true',
                        help='keep the other runs of the existing results file (each exclusive '
                             'CPU slot stays short: run the scenes in two invocations)')
    opts = parser.parse_args(argv)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    runs: Dict[str, Any] = {}
    previous = results_dir() / f'{opts.out_name}.json'
    old_notes: List[str] = []
    if opts.update and previous.is_file():
        old = json.loads(previous.read_text())
        runs.update(old.get('runs', {}))
        old_notes = [n for n in old.get('notes', []) if n not in NOTES]
    for spec in opts.runs:
        parts = spec.split(':')
        scene, rate, peer = parts[0], float(parts[1]), len(parts) > 2 and parts[2] == 'peer'
        key = f'{scene}@{rate:g}Hz' + (' (peer: main configuration)' if peer else '')
        print(f'== {key}', flush=True)
        try:
            runs[key] = run_graph(scene, rate, opts.seconds, peer)
        except RuntimeError as exc:
            print(f'   failed: {exc}', flush=True)
            runs[key] = {'error': str(exc)}
            continue
        r = runs[key]
        print(f"   camera {r['camera_rate_measured_hz']:.2f} Hz; final {r['final_topic']} "
              f"{r['final_rate_hz']:.2f} Hz, latency median {r['final_latency_ms']['median']:.1f}"
              f" p90 {r['final_latency_ms']['p90']:.1f} max {r['final_latency_ms']['max']:.1f} "
              f'ms; dropped before the last node '
              f"{100 * r['dropped_before_last_node_fraction']:.1f} %; load "
              f"{r['load_average_1min']['end']:.2f}", flush=True)
        for topic, t in r['topics'].items():
            print(f"     {topic}: {t['rate_hz']:.2f} Hz, latency median "
                  f"{t['latency_ms']['median']:.1f} p90 {t['latency_ms']['p90']:.1f} max "
                  f"{t['latency_ms']['max']:.1f} ms, missing {t['frames_missing']}", flush=True)
        print('     CPU % of one core: ' + ', '.join(
            f'{n} {v:.0f}' for n, v in r['cpu_percent_of_one_core'].items()), flush=True)

    for key, r in runs.items():
        if 'error' not in r:
            r['cpu_ms_per_output_frame'] = cpu_per_frame(r)
            r['cpu_ms_per_camera_frame'] = cpu_per_camera_frame(r)
            print(f'{key}: CPU ms per camera frame: ' + ', '.join(
                f'{n} {v:.1f}' for n, v in r['cpu_ms_per_camera_frame'].items()))
    goals = []
    nan = float('nan')
    r10 = runs.get('peg_in_hole@10Hz', {})
    r30 = runs.get('peg_in_hole@30Hz', {})
    # ">= 10 Hz" at a 10 Hz camera: rclpy's timer delivers 9.998 Hz over a 30 s window, so the
    # rate target allows the timer 1 % (RATE_TARGET_HZ) and a second goal asks for every
    # camera frame to reach the corrected pose
    goals.append(goal('peg_in_hole_10hz_corrected_pose_rate_hz', RATE_TARGET_HZ, '>=',
                      r10.get('final_rate_hz', nan) if 'error' not in r10 else nan))
    fin = r10.get('topics', {}).get(FINAL_TOPIC['peg_in_hole'], {})
    goals.append(goal('peg_in_hole_10hz_camera_frames_with_corrected_pose_percent', 100.0, '>=',
                      100.0 * (1.0 - fin.get('frames_missing_fraction', nan))))
    goals.append(goal('peg_in_hole_10hz_corrected_pose_latency_p90_ms', 100.0, '<=',
                      r10.get('final_latency_ms', {}).get('p90', nan)))
    goals.append(goal('peg_in_hole_10hz_frames_dropped_before_contact_node_percent', 0.0, '<=',
                      100 * r10.get('dropped_before_last_node_fraction', nan)))
    goals.append(goal('peg_in_hole_30hz_corrected_pose_latency_max_ms', opts.bound_ms, '<=',
                      r30.get('final_latency_ms', {}).get('max', nan)))
    goals.append(goal('peg_in_hole_30hz_corrected_pose_rate_hz', RATE_TARGET_HZ, '>=',
                      r30.get('final_rate_hz', nan)))
    ours = runs.get('primitives@10Hz', {}).get('topics', {})
    peer = runs.get('primitives@10Hz (peer: main configuration)', {}).get('topics', {})
    ip_topic = '/objects/cube/implicit_polynomial'
    ip_ours = ours.get(ip_topic, {}).get('latency_ms', {}).get('median', nan)
    ip_peer = peer.get(ip_topic, {}).get('latency_ms', {}).get('median', nan)
    goals.append(goal('primitives_ip_fit_latency_median_ratio_vs_peer', 1.0, '<',
                      ip_ours / ip_peer if ip_peer and ip_peer == ip_peer else nan))
    for scene in ('revolute_pair', 'primitives'):
        r = runs.get(f'{scene}@10Hz', {})
        goals.append(goal(f'{scene}_10hz_{FINAL_TOPIC[scene].strip("/").replace("/", "_")}'
                          '_rate_hz', RATE_TARGET_HZ, '>=', r.get('final_rate_hz', nan)))
    comparison = {}
    for scene in ('peg_in_hole', 'primitives'):
        a = runs.get(f'{scene}@10Hz', {})
        p = runs.get(f'{scene}@10Hz (peer: main configuration)', {})
        if 'topics' in a and 'topics' in p:
            comparison[scene] = {
                'final_rate_hz': {'ours': a['final_rate_hz'], 'peer': p['final_rate_hz']},
                'final_latency_median_ms': {'ours': a['final_latency_ms']['median'],
                                            'peer': p['final_latency_ms']['median']},
                'stereo_cpu_ms_per_frame': {
                    'ours': a['cpu_ms_per_output_frame'].get('stereo_depth_node', nan),
                    'peer': p['cpu_ms_per_output_frame'].get('stereo_depth_node', nan)},
                'load_average_1min_end': {'ours': a['load_average_1min']['end'],
                                          'peer': p['load_average_1min']['end']}}
    write_report(opts.out_name, goals, runs=runs, seconds_per_run=opts.seconds,
                 comparison_with_peer_same_run=comparison,
                 latency_bound_at_30hz_ms=opts.bound_ms,
                 notes=NOTES + old_notes + ([opts.note] if opts.note else []))
    return 0


if __name__ == '__main__':
    sys.exit(main())
