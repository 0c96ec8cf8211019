"""
The peg_in_hole graph split over several machines, simulated with network namespaces.

A real cell has the stereo camera on one computer, perception on another and the robot
controller on a third. :func:`run_graph` starts the demo's nodes (the same
``stereo_manip_bringup.demo`` specs) on simulated hosts of a
:class:`stereo_manip_tools.netns.VirtualLan` — or all on this host, the one-machine peer — with
the camera free-running, and a controller client (:mod:`stereo_manip_tools.pose_listener`)
on its own host logging every corrected pose on arrival. :func:`summarise` turns that log into
the corrected-pose rate, the end-to-end latency (arrival - camera stamp; the namespaces share
one clock) and the bytes each host sent over the LAN.

Every participant on the simulated LAN gets what a user of a multi-host cell gets
(:func:`stereo_manip_bringup.deployment.multihost_environment`: SUBNET discovery and the
shipped Fast DDS profile, UDPv4 only), or, for comparison, Fast DDS's defaults over UDPv4
(``dds='fastdds_defaults'``: 64 kB datagrams, system socket buffers). The one-host peer uses
the defaults: localhost discovery, shared memory.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import json
import os
from pathlib import Path
import subprocess
import sys
import tempfile
import time
from typing import Any, Dict, List, Optional, Sequence

import numpy as np

from stereo_manip_bringup.demo import NodeSpec, STAGES
from stereo_manip_bringup.deployment import multihost_environment
from stereo_manip_tools.processes import interrupt_then_kill, process_cpu_seconds

__all__ = ['HOSTS', 'peg_in_hole_placement', 'run_graph', 'summarise', 'GraphRun',
           'CORRECTED_TOPIC', 'TRUTH_TOPIC', 'ros_environment', 'DDS_CHOICES']

HOSTS = ('camera', 'perception', 'controller')
CORRECTED_TOPIC = '/objects/peg/pose_corrected'
TRUTH_TOPIC = '/objects/peg/pose_truth'


def peg_in_hole_placement(camera_rate: float, stereo_on_camera: bool = False,
                          stereo_parameters: Optional[Dict[str, Any]] = None,
                          frame_step: Optional[int] = None) -> Dict[str, List[NodeSpec]]:
    """
    Place the demo's peg_in_hole nodes on hosts.

    The demo's peg_in_hole nodes placed on hosts, the camera free-running at
    ``camera_rate`` [Hz], playing the scene at its own speed (30 fps nominal) back and forth
    from its first frame (where the localiser is initialised), as the live demo stage does.

    :param stereo_on_camera: run the stereo node on the camera host (the point cloud crosses
        the link instead of the image pair).
    :param stereo_parameters: extra stereo node parameters (e.g. a cloud decimation).
    :param frame_step: scene frames per camera frame (default: the scene's own speed,
        30 / ``camera_rate``; 1 plays it slowly, easy to track on a loaded machine).
    """
    camera, stereo, localizer, contact = STAGES['peg_in_hole']().nodes
    camera.parameters.update(trigger=False, rate=float(camera_rate), playback='bounce',
                             frame_step=int(frame_step) if frame_step else max(
                                 1, int(round(30.0 / camera_rate))))
    camera.remappings.pop('trigger', None)
    stereo.parameters.update(stereo_parameters or {})
    if stereo_on_camera:
        return {'camera': [camera, stereo], 'perception': [localizer, contact]}
    return {'camera': [camera], 'perception': [stereo, localizer, contact]}


@dataclass
class GraphRun:
    """What :func:`run_graph` observed: the controller's log and each process's output."""

    poses: List[Dict[str, Any]]
    logs: Dict[str, str]
    camera_start_wall_ns: int
    end_wall_ns: int
    switch_stats: Optional[Dict[str, Any]] = None
    switch_samples: List[Dict[str, Any]] = field(default_factory=list)
    counters: Dict[str, Dict[str, int]] = field(default_factory=dict)
    exit_codes: Dict[str, Optional[int]] = field(default_factory=dict)
    ready_s: float = float('nan')
    cpu_fraction: Dict[str, float] = field(default_factory=dict)   # of one core, camera on


DDS_CHOICES = ('multihost_profile', 'fastdds_defaults')


def ros_environment(domain_id: int, over_lan: bool,
                    dds: str = 'multihost_profile') -> Dict[str, str]:
    """
    Environment of every participant.

    One domain; over the simulated LAN the multi-host environment a user gets
    (``dds='multihost_profile'``) or Fast DDS's defaults over UDPv4 (``'fastdds_defaults'``, SUBNET
    discovery); on one host localhost discovery and Fast DDS defaults (shared memory).
    """
    if dds not in DDS_CHOICES:
        raise ValueError(f'dds must be one of {DDS_CHOICES}, got {dds!r}')
    env = dict(os.environ)
    env['ROS_DOMAIN_ID'] = str(int(domain_id))
    env['PYTHONUNBUFFERED'] = '1'
    for key in ('ROS_STATIC_PEERS', 'FASTDDS_BUILTIN_TRANSPORTS',
                'FASTRTPS_DEFAULT_PROFILES_FILE'):
        env.pop(key, None)
    if over_lan and dds == 'multihost_profile':
        env.update(multihost_environment())
    elif over_lan:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'SUBNET'
        env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    else:
        env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    return env


class _Proc:
    def __init__(self, name: str, argv: List[str], env: Dict[str, str], log_dir: Path) -> None:
        self.name = name
        self.log_path = log_dir / f'{name}.log'
        self._log = open(self.log_path, 'w')
        self.popen = subprocess.Popen(argv, stdout=self._log, stderr=subprocess.STDOUT, env=env)

    def output(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_path.read_text(errors='replace')

    def stop(self, timeout: float = 10.0) -> Optional[int]:
        code = interrupt_then_kill(self.popen, timeout)
        if not self._log.closed:
            self._log.close()
        return code


def _stop_all(procs: List[_Proc], run: GraphRun) -> None:
    """
    Stop every process (SIGINT, SIGKILL after 10 s), also when interrupted half-way.

    a second Ctrl-C or an error while stopping one must not leave the others running.
    """
    try:
        for p in reversed(procs):
            run.exit_codes[p.name] = p.stop()
            run.logs[p.name] = p.output() if p.log_path.exists() else ''
    finally:
        for p in procs:
            if p.popen.poll() is None:
                p.popen.kill()
                try:
                    p.popen.wait(5)
                except subprocess.TimeoutExpired:
                    pass


def run_graph(placement: Dict[str, List[NodeSpec]], duration: float, domain_id: int,
              lan: Any = None, controller_host: str = 'controller',
              ready_timeout: float = 120.0, log_dir: Optional[Path] = None,
              log: Any = print, stop_after_corrected: int = 0,
              extra_env: Optional[Dict[str, Optional[str]]] = None,
              dds: str = 'multihost_profile') -> GraphRun:
    """
    Start the graph, then the camera; listen on the controller; stop everything.

    Start the graph, then the camera when every perception subscription is matched, listen
    ``duration`` s on the controller, stop everything (SIGINT, then SIGKILL).

    :param placement: host -> nodes (from :func:`peg_in_hole_placement`).
    :param lan: a created ``VirtualLan`` holding every host of ``placement`` and
        ``controller_host``, or None to run every process on this host (the one-host peer).
    :param stop_after_corrected: end early once the controller logged this many corrected
        poses (0: run the whole ``duration``).
    :param extra_env: added to every participant's environment (e.g. a Fast DDS profile);
        a None value removes that variable.
    :param dds: DDS configuration over the LAN (see :func:`ros_environment`).
    :raises RuntimeError: the graph did not come up within ``ready_timeout`` s or a node died
        (with the tails of every log).
    """
    from stereo_manip_tools.processes import executable_path

    env = ros_environment(domain_id, lan is not None, dds)
    for key, value in (extra_env or {}).items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    log_dir = Path(log_dir or tempfile.mkdtemp(prefix='multihost_'))
    log_dir.mkdir(parents=True, exist_ok=True)

    def argv_on(host: str, argv: List[str]) -> List[str]:
        return lan.command(host, argv) if lan is not None else argv

    procs: List[_Proc] = []
    camera: Optional[_Proc] = None
    poses_path = log_dir / 'controller_poses.jsonl'
    t_camera = time.time_ns()
    switch_samples: List[Dict[str, Any]] = []
    run = GraphRun([], {}, 0, 0)
    try:
        camera_specs = []
        wait_topics = []
        for host, specs in placement.items():
            for spec in specs:
                if spec.executable == 'synthetic_camera':
                    camera_specs.append((host, spec))
                    continue
                argv = [str(executable_path(spec.package, spec.executable)), '--ros-args',
                        *spec.ros_args()]
                procs.append(_Proc(f'{host}.{spec.node_name}', argv_on(host, argv),
                                   {**env, **getattr(spec, 'env', {})}, log_dir))
        wait_topics = ['/left/image_rect', '/points2', '/objects/peg/pose']
        listener = _Proc(f'{controller_host}.pose_listener', argv_on(controller_host, [
            sys.executable, '-m', 'stereo_manip_tools.pose_listener', '--out', str(poses_path),
            '--duration', str(duration + ready_timeout), '--wait-subscribed', *wait_topics,
            '--', CORRECTED_TOPIC, TRUTH_TOPIC]), env, log_dir)
        procs.append(listener)
        t0 = time.monotonic()
        while 'graph ready' not in listener.output():
            dead = [p.name for p in procs if p.popen.poll() is not None]
            if dead or time.monotonic() - t0 > ready_timeout:
                raise RuntimeError(
                    ('process(es) exited early: ' + ', '.join(dead)) if dead else
                    f'the graph was not ready within {ready_timeout} s (the controller host '
                    f'did not see subscribers on {", ".join(wait_topics)})')
            time.sleep(0.2)
        run.ready_s = time.monotonic() - t0
        log(f'  graph ready after {run.ready_s:.1f} s; starting the camera')
        t_camera = time.time_ns()
        for host, spec in camera_specs:
            argv = [str(executable_path(spec.package, spec.executable)), '--ros-args',
                    *spec.ros_args()]
            camera = _Proc(f'{host}.{spec.node_name}', argv_on(host, argv),
                           {**env, **getattr(spec, 'env', {})}, log_dir)
            procs.append(camera)
        t_end = time.monotonic() + duration
        cpu0 = {p.name: process_cpu_seconds(p.popen.pid) for p in procs}
        t_cpu0 = time.monotonic()
        next_sample = time.monotonic()
        while time.monotonic() < t_end:
            dead = [p.name for p in procs if p.popen.poll() is not None]
            if dead:
                raise RuntimeError('process(es) exited early: ' + ', '.join(dead))
            if stop_after_corrected and poses_path.exists() and poses_path.read_text().count(
                    CORRECTED_TOPIC) >= stop_after_corrected:
                break
            if lan is not None and time.monotonic() >= next_sample:
                stats = lan.switch_stats()
                if stats:
                    switch_samples.append({'wall_ns': time.time_ns(), **stats})
                next_sample += 1.0
            time.sleep(0.1)
        run.end_wall_ns = time.time_ns()
        elapsed = time.monotonic() - t_cpu0
        run.cpu_fraction = {p.name: (process_cpu_seconds(p.popen.pid) - cpu0.get(p.name, 0.0))
                            / elapsed for p in procs}
        if lan is not None:
            run.counters = {h: {**lan.counters(h), **lan.ip_stats(h)} for h in lan.hosts}
    except RuntimeError as exc:
        for p in procs:
            p.stop()
        tails = '\n'.join(f'--- {p.name}\n{p.output()[-2500:]}' for p in procs)
        raise RuntimeError(f'{exc}\n{tails}') from None
    finally:
        _stop_all(procs, run)
    run.camera_start_wall_ns = t_camera
    run.switch_samples = switch_samples
    if lan is not None:
        run.switch_stats = lan.switch_stats()
    if poses_path.exists():
        run.poses = [json.loads(line) for line in poses_path.read_text().splitlines()
                     if line.strip()]
    return run


def _stats(values: Sequence[float]) -> Dict[str, float]:
    v = np.asarray(values, float)
    if v.size == 0:
        return {'n': 0, 'p50': float('nan'), 'p90': float('nan'), 'p95': float('nan'),
                'max': float('nan')}
    return {'n': int(v.size), 'p50': float(np.median(v)), 'p90': float(np.percentile(v, 90)),
            'p95': float(np.percentile(v, 95)), 'max': float(v.max())}


def summarise(run: GraphRun, warmup: float = 5.0,
              model_points: Optional[np.ndarray] = None) -> Dict[str, Any]:
    """
    Summarise the pose, camera and link figures of a run.

    Pose figures over the window from ``warmup`` s after the first corrected pose to the
    end of the run; camera and link figures from ``warmup`` s after the camera started.

    :returns: corrected poses in the window, their rate [Hz] over arrival times, latency
        [ms] (arrival - camera stamp) p50/p90/p95/max, gaps between arrivals, the fraction of
        camera frames (truth poses seen by the controller) that produced a corrected pose; the
        camera rate the controller saw; per host the bytes per second it sent over the LAN
        (switch counters), the switch's CPU and lateness; with ``model_points`` (peg model,
        metres) the ADD-S error [mm] of each corrected pose vs the camera's truth for the same
        stamp (p50/p90/p95/max).
    """
    corrected = [p for p in run.poses if p['topic'] == CORRECTED_TOPIC]
    truth = [p for p in run.poses if p['topic'] == TRUTH_TOPIC]
    out: Dict[str, Any] = {'corrected_total': len(corrected), 'camera_frames_total': len(truth)}
    # link figures over the camera's run after the same warm-up, with or without poses
    t_link = run.camera_start_wall_ns + int(warmup * 1e9)
    seen = [p for p in truth if t_link <= p['stamp_ns'] <= run.end_wall_ns - int(1e9)]
    out['camera_rate_hz'] = len(seen) / max((run.end_wall_ns - int(1e9) - t_link) / 1e9, 1e-9)
    samples = [s for s in run.switch_samples if t_link <= s['wall_ns'] <= run.end_wall_ns]
    if len(samples) >= 2:
        a, b = samples[0], samples[-1]
        dt = (b['wall_ns'] - a['wall_ns']) / 1e9
        out['link'] = {}
        for ns, hb in b['hosts'].items():
            ha = a['hosts'][ns]
            host = ns.split('_', 1)[1]
            out['link'][host] = {
                'sent_bytes_per_s': (hb['sent_bytes'] - ha['sent_bytes']) / dt,
                'sent_mbit_per_s': (hb['sent_bytes'] - ha['sent_bytes']) * 8 / dt / 1e6,
                'received_mbit_per_s': (hb['delivered_bytes'] - ha['delivered_bytes'])
                * 8 / dt / 1e6,
                'frames_lost': hb['lost_frames'] - ha['lost_frames'],
                'frames_sent': hb['sent_frames'] - ha['sent_frames']}
        out['switch_cpu_fraction'] = (b['cpu_seconds'] - a['cpu_seconds']) / max(
            b['seconds'] - a['seconds'], 1e-9)
        out['switch_lateness_ms'] = {k: v * 1e3 if k != 'n' else v
                                     for k, v in b['lateness_s'].items()}
    if not corrected:
        return out
    t_first = min(p['arrival_ns'] for p in corrected)
    t0 = t_first + int(warmup * 1e9)
    t1 = run.end_wall_ns
    win = [p for p in corrected if t0 <= p['arrival_ns'] <= t1]
    frames = [p for p in truth if t0 <= p['stamp_ns'] <= t1 - int(1e9)]
    out['first_corrected_after_camera_start_s'] = (t_first - run.camera_start_wall_ns) / 1e9
    out['window_s'] = (t1 - t0) / 1e9
    out['corrected_in_window'] = len(win)
    arrivals = np.array(sorted(p['arrival_ns'] for p in win), float) / 1e9
    # poses per second over the whole window: a stream that stops early counts as stopped
    out['rate_hz'] = float(len(win) / out['window_s']) if out['window_s'] > 0 else 0.0
    out['last_corrected_before_end_s'] = (t1 - max(p['arrival_ns'] for p in corrected)) / 1e9
    out['latency_ms'] = _stats([(p['arrival_ns'] - p['stamp_ns']) / 1e6 for p in win])
    gaps = np.diff(arrivals) * 1e3 if len(arrivals) > 1 else []
    out['gap_ms'] = _stats(gaps)
    stamps = {p['stamp_ns'] for p in win}
    if model_points is not None:
        from object_localizer.evaluation import add_s
        from stereo_manip_tools.transforms import make_transform, matrix_from_quaternion

        def matrix(pose: Sequence[float]) -> np.ndarray:
            return make_transform(matrix_from_quaternion(np.array(pose[3:])),
                                  np.array(pose[:3]))
        by_stamp = {p['stamp_ns']: p for p in truth}
        errors = [add_s(matrix(p['pose']), matrix(by_stamp[p['stamp_ns']]['pose']),
                        model_points) * 1e3 for p in win if p['stamp_ns'] in by_stamp]
        out['add_s_corrected_mm'] = _stats(errors)
    out['camera_frames_in_window'] = len(frames)
    out['frames_with_corrected_pose'] = float(
        sum(p['stamp_ns'] in stamps for p in frames) / len(frames)) if frames else 0.0
    return out
