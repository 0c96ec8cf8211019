"""
Benchmark: reliability of the node graph (issue 16).

Benchmark: reliability of the node graph (issue 16) - fuzzing, kill -9 / restart, soak,
recorder under signals.

Sections (``--sections``, default all; each run merges its sections into the JSON):

- ``fuzz``: every subscriber of every node (processes from the install tree) gets
  hypothesis-generated malformed messages in bursts; after each burst a good input whose output
  is checked against what it must be (tests/fuzz_targets.py). Goal per node: >= 1000 malformed
  messages, 0 crashes, the good input processed correctly after every burst.
- ``kill``: the peg_in_hole graph (synthetic camera free-running at 10 Hz -> stereo ->
  localizer -> contact correction) runs; each node in turn is killed with SIGKILL mid-stream
  and restarted at once; measured: seconds from the kill until a contact-corrected peg pose
  of a frame taken after the kill arrives (goal <= 10 s), that no other node restarted, and
  the corrected poses' ADD-S error against the camera's ground truth before and after.
- ``soak``: the same graph for ``--soak-minutes`` (10) at 10 Hz: RSS of every node sampled
  every 5 s (growth = median of the last minute / median of the minute after the 2-minute
  warm-up - 1, goal <= 10 %), per-node latency (receipt of the node's output minus receipt of
  its input of the same stamp) p50/p95/p99/max in the first and second half after warm-up
  (goal: p99 of the second half <= 1.5x the first: not growing).
- ``recorder``: ``record`` under SIGINT, SIGTERM and SIGKILL while a 200 Hz stream goes on
  (tests/recorder_trials.py): published before the signal vs recorded; goals 0 lost for
  SIGINT/SIGTERM, bag readable as a gap-free prefix after SIGKILL.

Run: ``python bench/reliability.py`` (ROS_DOMAIN_ID set; about 35 min; ``--quick`` for a
smoke run). Writes ``bench/results/reliability.json``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path
import signal
import sys
import tempfile
import time
from typing import Any, Dict, List, Optional, Sequence, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))

import numpy as np  # noqa: E402

from stereo_manip_tools.bench_report import goal, results_dir, write_report  # noqa: E402

NAME = 'reliability'
NS = '/reliability'          # the graph's namespace (apart from the fuzz targets' topics)
#                              (--namespace: a kill run and a soak run in parallel)


def _stats(values: List[float]) -> Dict[str, float]:
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if not a.size:
        return {'count': 0, 'median': float('nan'), 'p95': float('nan'), 'p99': float('nan'),
                'max': float('nan')}
    return {'count': int(a.size), 'median': float(np.median(a)),
            'p95': float(np.percentile(a, 95)), 'p99': float(np.percentile(a, 99)),
            'max': float(a.max())}


# --- fuzz -----------------------------------------------------------------------------------

class _FuzzDone(Exception):
    """Raised in the hypothesis test once enough cases ran (ends the generation)."""


def run_fuzz(cases_per_node: int, names: List[str], log) -> Dict[str, Any]:
    from hypothesis import given, HealthCheck, Phase, settings
    from fuzz_targets import TARGETS
    from stereo_manip_tools.fuzzing import burst_strategy, FuzzSession

    out: Dict[str, Any] = {}
    for name in names:
        target = TARGETS[name]()
        t0 = time.monotonic()
        session = FuzzSession(target)
        results = []
        warm = session.run_cycle([], timeout=120.0)
        state = {'cases': 0}

        @settings(max_examples=cases_per_node + 50, deadline=None, database=None,
                  phases=[Phase.generate], suppress_health_check=list(HealthCheck),
                  report_multiple_bugs=False)
        @given(burst=burst_strategy(target, 5, 15))
        def run(burst):
            if state['cases'] >= cases_per_node:
                raise _FuzzDone()            # stops hypothesis generating further examples
            r = session.run_cycle(burst)
            results.append(r)
            state['cases'] += r.cases
            if len(results) % 10 == 0:
                log(f'  fuzz {name}: {state["cases"]} cases, {len(results)} bursts, '
                    f'{session.crashes} crashes, '
                    f'{sum(not x.good_ok for x in results)} good inputs missed')
        large = None
        try:
            try:
                run()
            except _FuzzDone:
                pass
            cloud_topics = [t for t, (cls, _) in target.inputs.items()
                            if cls.__name__ == 'PointCloud2']
            if cloud_topics:
                # bounded work: a 1 M-point random cloud, then the good input
                from stereo_manip_tools.conversions import xyz_to_pointcloud2
                P = np.random.default_rng(1).random((1_000_000, 3)) * 2.0 + [-1, -1, 0.2]
                large = session.run_cycle([(cloud_topics[0], xyz_to_pointcloud2(P))],
                                          timeout=120.0)
        finally:
            output = session.close()
        missed = [r.reason for r in results if not r.good_ok]
        out[name] = {
            'cases': state['cases'], 'bursts': len(results), 'crashes': session.crashes,
            'good_processed_after_burst': sum(r.good_ok for r in results),
            'good_missed_after_burst': len(missed), 'missed_reasons': sorted(set(missed))[:10],
            'warm_up_good_ok': warm.good_ok,
            'seconds_to_good_output': _stats([r.seconds_to_good_output for r in results]),
            'wall_time_s': time.monotonic() - t0,
            'million_point_cloud': None if large is None else {
                'crashed': large.crashed, 'good_ok': large.good_ok, 'reason': large.reason,
                'seconds_to_good_output': large.seconds_to_good_output},
            'crash_log_tails': [c[-1500:] for c in session.crash_logs[:3]],
            'tracebacks_in_output': output.count('Traceback'),
        }
        summary = {k: v for k, v in out[name].items() if k != 'crash_log_tails'}
        log(f'  fuzz {name}: {json.dumps(summary, default=str)[:600]}')
    return out


# --- the peg_in_hole graph ------------------------------------------------------------------

def graph_specs(rate: float) -> List[Any]:
    """
    Describe the demo's peg_in_hole graph with the camera free-running at ``rate`` Hz.

    The demo's peg_in_hole graph (stereo_manip_bringup.demo) with the camera free-running at
    ``rate`` Hz, one scene frame per camera frame (the scene loops every 225 frames: 22.5 s at
    10 Hz; at the loop the peg jumps 18 cm); remappings made relative, so the whole graph lives
    in the namespace NS.
    """
    from stereo_manip_bringup.demo import _peg_in_hole_stage, NodeSpec
    specs = []
    for spec in _peg_in_hole_stage('peg_in_hole_live', live_seconds=1.0).nodes:
        params = dict(spec.parameters)
        remaps = {a: b.lstrip('/') for a, b in spec.remappings.items()}
        if spec.executable == 'synthetic_camera':
            params.update(trigger=False, rate=float(rate), frame_step=1)
            remaps = {}
        specs.append(NodeSpec(spec.package, spec.executable, spec.node_name, params, remaps,
                              dict(spec.env)))
    return specs


def _stamp_of_cdr(data: bytes) -> int:
    """Header stamp [ns] of a CDR message that starts with a std_msgs/Header."""
    sec = int.from_bytes(data[4:8], 'little', signed=True)
    nsec = int.from_bytes(data[8:12], 'little')
    return sec * 1_000_000_000 + nsec


class Graph:
    """
    The graph as processes in namespace NS, and an observer.

    The graph as processes in namespace NS, and an observer taking raw messages (only the
    stamps are decoded, so watching the 3 MB clouds costs little).
    """

    TOPICS = {
        'truth': ('objects/peg/pose_truth', 'geometry_msgs/msg/PoseStamped'),
        'points2': ('points2', 'sensor_msgs/msg/PointCloud2'),
        'pose': ('objects/peg/pose', 'geometry_msgs/msg/PoseStamped'),
        'corrected': ('objects/peg/pose_corrected', 'geometry_msgs/msg/PoseStamped'),
    }

    def __init__(self, rate: float, keep_messages: Tuple[str, ...] = ()) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from stereo_manip_tools.bag_io import get_message_class
        from stereo_manip_tools.processes import make_node

        self.specs = {s.node_name: s for s in graph_specs(rate)}
        self.observer = make_node()
        self.arrivals: Dict[str, List[Tuple[int, float]]] = {k: [] for k in self.TOPICS}
        self.kept: Dict[str, List[Tuple[int, bytes]]] = {k: [] for k in keep_messages}
        self.classes = {}
        for key, (topic, type_name) in self.TOPICS.items():
            cls = get_message_class(type_name)
            self.classes[key] = cls
            reliable = key in ('points2',)
            qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE if reliable
                             else ReliabilityPolicy.BEST_EFFORT)
            self.observer.create_subscription(
                cls, f'{NS}/{topic}', lambda data, key=key: self._arrive(key, data), qos,
                raw=True)
        self.procs: Dict[str, Any] = {}

    def _arrive(self, key: str, data: bytes) -> None:
        stamp = _stamp_of_cdr(data)
        self.arrivals[key].append((stamp, time.monotonic()))
        if key in self.kept:
            self.kept[key].append((stamp, bytes(data)))

    def start_node(self, name: str, **parameters: Any) -> None:
        from stereo_manip_tools.processes import ExecutableProcess
        from stereo_manip_bringup.demo import NodeSpec
        spec = self.specs[name]
        if parameters:
            spec = NodeSpec(spec.package, spec.executable, spec.node_name,
                            {**spec.parameters, **parameters}, spec.remappings, spec.env)
        self.procs[name] = ExecutableProcess(spec.package, spec.executable, (),
                                             spec.ros_args() + ['-r', f'__ns:={NS}'],
                                             env=spec.env)

    def start(self) -> None:
        # the free-running camera last, once its readers are up (as the demo does)
        order = sorted(self.specs, key=lambda n: self.specs[n].executable == 'synthetic_camera')
        for name in order:
            self.start_node(name)
            if not self.procs[name].wait_for_node(self.observer, name, 120.0):
                raise RuntimeError(f'{name} did not start:\n{self.procs[name].output()[-3000:]}')
            if self.specs[name].executable == 'stereo_depth_node':
                self.procs[name].wait_for_output('warm-up', 60.0)       # kernels loaded

    def spin(self, seconds: float) -> None:
        from stereo_manip_tools.processes import spin_until
        spin_until(self.observer, lambda: False, seconds)

    def spin_until(self, predicate, timeout: float) -> bool:
        from stereo_manip_tools.processes import spin_until
        return spin_until(self.observer, predicate, timeout)

    def pids(self) -> Dict[str, int]:
        return {n: p.process.pid for n, p in self.procs.items()}

    def dead(self) -> List[str]:
        return [n for n, p in self.procs.items() if not p.running()]

    def stop(self) -> Dict[str, str]:
        from stereo_manip_tools.processes import shutdown_node
        logs = {}
        for name, proc in reversed(list(self.procs.items())):
            proc.stop()
            logs[name] = proc.output()
            proc.__exit__(None, None, None)
        shutdown_node(self.observer)
        return logs


def _rss_mb(pid: int) -> float:
    try:
        for line in Path(f'/proc/{pid}/status').read_text().splitlines():
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float('nan')


class PoseJudge:
    """ADD-S [m] of the graph's corrected peg poses against the camera's truth (same stamp)."""

    def __init__(self, graph: 'Graph') -> None:
        from object_localizer.localization import prepare_model
        from stereo_manip_tools.mesh_io import find_model, load_obj
        self.graph = graph
        self.points = prepare_model(load_obj(find_model('peg'))).points
        self.errors: Dict[int, float] = {}

    def error(self, stamp: int, data: bytes) -> Optional[float]:
        """Return the ADD-S [m] of a corrected pose, cached by stamp (a kill trial asks again)."""
        if stamp not in self.errors:
            err = self.measure(stamp, data)
            if err is None:
                return None
            self.errors[stamp] = err
        return self.errors[stamp]

    def measure(self, stamp: int, data: bytes) -> Optional[float]:
        """Return the ADD-S [m] of any peg pose message against its stamp's truth (no cache)."""
        from rclpy.serialization import deserialize_message
        from object_localizer.evaluation import add_s
        from stereo_manip_tools.conversions import pose_to_matrix
        truth = next((d for s, d in reversed(self.graph.kept['truth']) if s == stamp), None)
        if truth is None:
            return None
        cls = self.graph.classes['truth']
        return float(add_s(pose_to_matrix(deserialize_message(data, cls).pose),
                           pose_to_matrix(deserialize_message(truth, cls).pose), self.points))


#: frames of one loop of the peg_in_hole scene (stereo_depth.synthetic.make_scene)
SCENE_FRAMES = 225

#: a corrected pose farther than this (ADD-S) from the truth is wrong (the demo's threshold)
WRONG_POSE_M = 0.005


# --- kill / restart -------------------------------------------------------------------------

def kill_trial(victim: str, rate: float, timeout: float, log) -> Dict[str, Any]:
    """
    Kill ``victim`` in a running graph, restart it and time the recovery.

    A fresh graph; steady corrected poses; SIGKILL ``victim`` and restart it at once; time until
    the first *correct* corrected pose (ADD-S <= WRONG_POSE_M) of a frame taken after the kill,
    and the wrong ones published meanwhile.
    """
    graph = Graph(rate, keep_messages=('truth', 'corrected'))
    judge = PoseJudge(graph)
    try:
        graph.start()
        if not graph.spin_until(lambda: len(graph.arrivals['corrected']) >= 20, 180.0):
            raise RuntimeError('no corrected poses from the graph:\n' + '\n'.join(
                f'--- {n}\n{p.output()[-1500:]}' for n, p in graph.procs.items()))
        # Kill once 20 corrected poses in a row were right; the window for the resumption ends
        # 0.5 s before the scene loops (at the loop the peg jumps 18 cm and the localiser must
        # re-acquire it, which would mix into the measurement). The scene frame is counted
        # from the camera's truth messages (frame 0 first; the camera starts last).

        def steady_ok() -> bool:
            last = graph.kept['corrected'][-20:]
            return len(last) == 20 and all(
                (e := judge.error(s, d)) is not None and e <= WRONG_POSE_M for s, d in last)

        def early_in_loop() -> bool:
            return steady_ok() and (len(graph.arrivals['truth']) - 1) % SCENE_FRAMES < 120
        graph.spin_until(early_in_loop, 60.0)
        before = len(graph.kept['corrected'])
        steady = [judge.error(s, d) for s, d in graph.kept['corrected'][-20:]]
        frame = (len(graph.arrivals['truth']) - 1) % SCENE_FRAMES
        loop_start = time.monotonic() - frame / rate
        loop_end = loop_start + SCENE_FRAMES / rate
        pids_before = graph.pids()
        kill_wall_ns = time.time_ns()
        t_kill = time.monotonic()
        os.kill(pids_before[victim], signal.SIGKILL)
        graph.procs[victim].process.wait(10.0)
        killed_output = graph.procs[victim].output()[-2000:]
        if graph.specs[victim].executable == 'synthetic_camera':
            # a real camera's world goes on: the restarted synthetic camera continues the scene
            graph.start_node(victim, start_frame=frame)
        else:
            graph.start_node(victim)
        t_restart = time.monotonic()
        first_any: List[float] = []
        first_ok: List[float] = []

        def resumed() -> bool:
            items = graph.kept['corrected'][before:]     # appended with its arrival
            arrivals = graph.arrivals['corrected'][before:]
            for (s, d), (_, t) in zip(items, arrivals):
                if s <= kill_wall_ns:
                    continue
                if not first_any:
                    first_any.append(t)
                err = judge.error(s, d)
                if err is not None and err <= WRONG_POSE_M:
                    first_ok.append(t)
                    return True
            return False
        window = timeout if loop_end is None else min(timeout, loop_end - 0.5 - time.monotonic())
        graph.spin_until(resumed, max(window, 0.0))
        # only poses of frames before the loop count (after it the peg has jumped)
        if loop_end is not None:
            loop_wall_ns = kill_wall_ns + int((loop_end - t_kill) * 1e9)
        else:
            loop_wall_ns = 2**63 - 1
        graph.spin(max(min(3.0, loop_end - 0.5 - time.monotonic()) if loop_end else 3.0, 0.0))
        after = [(s, judge.error(s, d)) for s, d in graph.kept['corrected'][before:]
                 if kill_wall_ns < s < loop_wall_ns]
        errors_after = [e for _, e in after if e is not None]
        others = {n: graph.procs[n].process.pid == pids_before[n] and graph.procs[n].running()
                  for n in graph.specs if n != victim}
        t_ok = first_ok[0] if first_ok else None
        result = {
            'resume_window_s': window,
            'steady_state_correct_before_kill': bool(steady) and all(
                e is not None and e <= WRONG_POSE_M for e in steady),
            'scene_frame_at_kill': frame,
            'resumed_correct': t_ok is not None,
            'seconds_kill_to_correct_corrected_pose': (t_ok - t_kill) if t_ok else None,
            'seconds_restart_to_correct_corrected_pose': (t_ok - t_restart) if t_ok else None,
            'seconds_kill_to_any_corrected_pose': (first_any[0] - t_kill) if first_any
            else None,
            'wrong_poses_after_kill': sum(e > WRONG_POSE_M for e in errors_after),
            'poses_after_kill': len(after),
            'other_nodes_untouched': all(others.values()), 'others': others,
            'add_s_mm_steady_before_kill': _stats([e * 1e3 for e in steady if e is not None]),
            'add_s_mm_after_kill': _stats([e * 1e3 for e in errors_after]),
            'victim_running': graph.procs[victim].running(),
            'killed_output_tail': killed_output[-800:],
        }
    finally:
        logs = graph.stop()
    result['victim_output_after_restart_tail'] = logs.get(victim, '')[-1500:]
    return result


def run_kill(rate: float, timeout: float, log, victims: Sequence[str] = ()) -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    for victim in victims or [s.node_name for s in graph_specs(rate)]:
        out[victim] = kill_trial(victim, rate, timeout, log)
        log(f'  kill {victim}: ' + json.dumps(
            {k: v for k, v in out[victim].items() if not k.endswith('_tail')},
            default=str)[:700])
    return out


# --- soak -------------------------------------------------------------------------------------

def run_soak(rate: float, minutes: float, warmup_s: float, log) -> Dict[str, Any]:
    graph = Graph(rate, keep_messages=('truth', 'pose', 'corrected'))
    rss: Dict[str, List[Tuple[float, float]]] = {}
    loads: List[Tuple[float, float]] = []
    try:
        graph.start()
        pids = graph.pids()
        t0 = time.monotonic()
        end = t0 + minutes * 60.0
        next_sample = t0
        while time.monotonic() < end:
            graph.spin(min(1.0, max(end - time.monotonic(), 0.0)))
            now = time.monotonic()
            if now >= next_sample:
                for name, pid in pids.items():
                    rss.setdefault(name, []).append((now - t0, _rss_mb(pid)))
                loads.append((round(now - t0, 1), os.getloadavg()[0]))
                next_sample += 5.0
                if int(now - t0) % 60 < 5:
                    log(f'  soak {now - t0:.0f} s: ' + ', '.join(
                        f'{n} {v[-1][1]:.0f} MB' for n, v in rss.items()) + ', corrected '
                        f'{len(graph.arrivals["corrected"])}; dead: {graph.dead()}')
        dead = graph.dead()
        restarted = {n: graph.procs[n].process.pid != pids[n] for n in pids}
    finally:
        logs = graph.stop()
    span = minutes * 60.0
    out: Dict[str, Any] = {'minutes': minutes, 'rate_hz': rate, 'warmup_s': warmup_s,
                           'dead_at_end': dead, 'restarted': restarted,
                           'camera_frames': len(graph.arrivals['truth']),
                           'clouds': len(graph.arrivals['points2']),
                           'poses': len(graph.arrivals['pose']),
                           'corrected_poses': len(graph.arrivals['corrected'])}
    out['output_rate_hz'] = {k: len(v) / span for k, v in graph.arrivals.items()}
    judge = PoseJudge(graph)
    corrected = {st: judge.error(st, d) for st, d in graph.kept['corrected']}
    errs = [corrected[st] for st, _ in graph.kept['corrected'] if corrected[st] is not None]
    out['corrected_add_s_mm'] = _stats([e * 1e3 for e in errs])
    out['corrected_wrong_fraction'] = (sum(e > WRONG_POSE_M for e in errs) / len(errs)
                                       if errs else float('nan'))
    # where a wrong corrected pose came from: the localizer's pose of the same stamp, judged
    raw = {st: judge.measure(st, d) for st, d in graph.kept['pose']}
    raw_errs = [e for e in raw.values() if e is not None]
    out['raw_add_s_mm'] = _stats([e * 1e3 for e in raw_errs])
    out['raw_wrong_fraction'] = (sum(e > WRONG_POSE_M for e in raw_errs) / len(raw_errs)
                                 if raw_errs else float('nan'))
    frame_of = {st: i for i, (st, _) in enumerate(graph.arrivals['truth'])}
    out['wrong_corrected_frames'] = [
        {'camera_frame_index': frame_of.get(st), 'corrected_add_s_mm': e * 1e3,
         'raw_add_s_mm': None if raw.get(st) is None else raw[st] * 1e3}
        for st, e in corrected.items() if e is not None and e > WRONG_POSE_M]
    graph.kept.clear()
    out['loadavg_1min_samples'] = loads
    growth = {}
    for name, samples in rss.items():
        t = np.array([s[0] for s in samples])
        m = np.array([s[1] for s in samples])
        first = m[(t >= warmup_s) & (t < warmup_s + 60.0)]
        last = m[t >= t[-1] - 60.0]
        growth[name] = {'rss_mb_after_warmup': float(np.median(first)) if first.size else None,
                        'rss_mb_last_minute': float(np.median(last)) if last.size else None,
                        'rss_mb_max': float(np.nanmax(m)),
                        'growth_fraction': float(np.median(last) / np.median(first) - 1.0)
                        if first.size and last.size else float('nan'),
                        'samples': [[round(a, 1), round(b, 1)] for a, b in samples]}
    out['rss'] = growth
    # per-node latency: the node's output receipt minus its input's receipt, same stamp
    arrive = {k: {} for k in graph.arrivals}
    for k, v in graph.arrivals.items():
        for s, t in v:
            arrive[k].setdefault(s, t)
    t_origin = min((t for v in graph.arrivals.values() for _, t in v[:1]), default=0.0)
    mid = t_origin + warmup_s + (span - warmup_s) / 2.0
    lat: Dict[str, Any] = {}
    for node, (src, dst) in {'stereo_depth_node': ('truth', 'points2'),
                             'object_localizer': ('points2', 'pose'),
                             'contact_correction': ('pose', 'corrected'),
                             'end_to_end': ('truth', 'corrected')}.items():
        pairs = [(arrive[src][s], arrive[dst][s] - arrive[src][s]) for s in arrive[dst]
                 if s in arrive[src]]
        pairs = [(t, d) for t, d in pairs if t >= t_origin + warmup_s]
        first = [d for t, d in pairs if t < mid]
        second = [d for t, d in pairs if t >= mid]
        s1, s2 = _stats(first), _stats(second)
        minutes_p99 = []
        for m0 in np.arange(t_origin + warmup_s, t_origin + span, 60.0):
            window = [d for t, d in pairs if m0 <= t < m0 + 60.0]
            minutes_p99.append(_stats(window)['p99'])
        lat[node] = {'first_half_s': s1, 'second_half_s': s2,
                     'p99_ratio_second_to_first': s2['p99'] / s1['p99']
                     if s1['count'] and s2['count'] else float('nan'),
                     'p99_per_minute_s': minutes_p99}
    out['latency'] = lat
    out['log_tails'] = {k: v[-1500:] for k, v in logs.items()}
    return out


# --- recorder ------------------------------------------------------------------------------

def run_recorder(log) -> Dict[str, Any]:
    from recorder_trials import recorder_trial
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            r = recorder_trial(Path(tmp), sig, before_s=5.0, rate_hz=200.0, flush_period=0.5)
            out[r['signal']] = r
            log(f'  recorder {r["signal"]}: published before {r["published_before_signal"]}, '
                f'recorded {r["recorded"]}, lost {r["lost_before_signal"]}, readable '
                f'{r["readable"]}, closed {r["closed_cleanly"]}')
    return out


# --- goals ---------------------------------------------------------------------------------

def goals_of(sections: Dict[str, Any], cases_goal: int) -> List[Dict[str, Any]]:
    goals = []
    for name, r in sorted(sections.get('fuzz', {}).items()):
        goals.append(goal(f'fuzz_{name}_malformed_messages', cases_goal, '>=', r['cases']))
        goals.append(goal(f'fuzz_{name}_crashes', 0, '==', r['crashes']))
        goals.append(goal(f'fuzz_{name}_good_input_missed_after_burst', 0, '==',
                          r['good_missed_after_burst'] + (0 if r['warm_up_good_ok'] else 1)))
        big = r.get('million_point_cloud')
        if big is not None:
            goals.append(goal(f'fuzz_{name}_seconds_to_good_output_after_1M_point_cloud', 10.0,
                              '<=', big['seconds_to_good_output'] if big['good_ok']
                              else float('nan')))
    for name, r in sorted(sections.get('kill', {}).items()):
        v = r['seconds_kill_to_correct_corrected_pose']
        goals.append(goal(f'kill9_{name}_seconds_to_correct_corrected_pose', 10.0, '<=',
                          v if v is not None else float('nan')))
        goals.append(goal(f'kill9_{name}_other_nodes_restarted', 0, '==',
                          sum(not ok for ok in r['others'].values())))
        goals.append(goal(f'kill9_{name}_wrong_corrected_poses_after_kill', 0, '==',
                          r['wrong_poses_after_kill']))
        goals.append(goal(f'kill9_{name}_steady_state_correct_before_kill', 1, '==',
                          int(r['steady_state_correct_before_kill'])))
    soak = sections.get('soak')
    if soak:
        goals.append(goal('soak_nodes_died', 0, '==', len(soak['dead_at_end'])))
        # not an acceptance point of the soak, shown because a wrong pose is worse than none
        goals.append(goal('soak_corrected_pose_wrong_fraction_add_s_over_5mm', 0.0, '<=',
                          soak.get('corrected_wrong_fraction', float('nan'))))
        for name, r in sorted(soak['rss'].items()):
            goals.append(goal(f'soak_{name}_rss_growth_fraction', 0.10, '<=',
                              r['growth_fraction']))
        for name, r in sorted(soak['latency'].items()):
            goals.append(goal(f'soak_{name}_latency_p99_second_to_first_half', 1.5, '<=',
                              r['p99_ratio_second_to_first']))
            goals.append(goal(f'soak_{name}_latency_p99_s', 3.0 if name == 'end_to_end' else 2.0,
                              '<=', r['second_half_s']['p99']))
    rec = sections.get('recorder')
    if rec:
        for sig in ('SIGINT', 'SIGTERM'):
            if sig in rec:
                goals.append(goal(f'recorder_{sig}_messages_lost', 0, '==',
                                  rec[sig]['lost_before_signal']
                                  + (0 if rec[sig]['closed_cleanly'] else 10**6)))
        if 'SIGKILL' in rec:
            r = rec['SIGKILL']
            goals.append(goal('recorder_SIGKILL_bag_readable_gap_free', 1, '==',
                              int(r['readable'] and r['gap_free_prefix'] and r['recorded'] > 0)))
    return goals


def main(argv: Optional[List[str]] = None) -> int:
    global NS
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--sections', nargs='+', default=['fuzz', 'kill', 'soak', 'recorder'],
                        choices=['fuzz', 'kill', 'soak', 'recorder'])
    parser.add_argument('--fuzz-cases', type=int, default=1000)
    parser.add_argument('--fuzz-nodes', nargs='+', default=None)
    parser.add_argument('--rate', type=float, default=10.0, help='camera rate [Hz]')
    parser.add_argument('--kill-timeout', type=float, default=60.0)
    parser.add_argument('--kill-nodes', nargs='+', default=None)
    parser.add_argument('--soak-minutes', type=float, default=10.0)
    parser.add_argument('--warmup', type=float, default=120.0)
    parser.add_argument('--quick', action='store_true',
                        help='smoke run: 30 fuzz cases, 2-minute soak (not a result)')
    parser.add_argument('--out', default=None, help='results directory')
    parser.add_argument('--namespace', default=NS, help='namespace of the graph')
    parser.add_argument('--merge', nargs='*', default=[],
                        help='reliability.json files of runs made in parallel (e.g. one per '
                             'fuzz node): their sections are merged in (fuzz per node)')
    opts = parser.parse_args(argv)
    if opts.quick:
        opts.fuzz_cases, opts.soak_minutes, opts.warmup = 30, 2.0, 30.0
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    NS = opts.namespace
    out_dir = Path(opts.out) if opts.out else results_dir()
    path = out_dir / f'{NAME}.json'
    previous = json.loads(path.read_text()) if path.exists() else {}
    sections = previous.get('sections', {})
    runs = dict(previous.get('runs', {}))
    for other in opts.merge:
        data = json.loads(Path(other).read_text())
        for key, value in data.get('sections', {}).items():
            if key in ('fuzz', 'kill'):
                sections.setdefault(key, {}).update(value)
            else:
                sections[key] = value
        for key, value in data.get('runs', {}).items():
            if key == 'fuzz':
                key = 'fuzz ' + ', '.join(sorted(data['sections'].get('fuzz', {})))
            runs[key] = value
    load = {'loadavg_start': os.getloadavg()}

    def log(text: str) -> None:
        print(text, flush=True)

    from fuzz_targets import TARGETS
    for section in (opts.sections if not opts.merge else []):
        t0 = time.monotonic()
        log(f'== {section}')
        if section == 'fuzz':
            names = opts.fuzz_nodes or sorted(TARGETS)
            result = dict(sections.get('fuzz', {}))
            result.update(run_fuzz(opts.fuzz_cases, names, log))
        elif section == 'kill':
            result = dict(sections.get('kill', {}))
            result.update(run_kill(opts.rate, opts.kill_timeout, log, opts.kill_nodes or ()))
        elif section == 'soak':
            result = run_soak(opts.rate, opts.soak_minutes, opts.warmup, log)
        else:
            result = run_recorder(log)
        sections[section] = result
        load[f'{section}_wall_time_s'] = time.monotonic() - t0
        load[f'loadavg_after_{section}'] = os.getloadavg()
    write_report(NAME, goals_of(sections, 1000), directory=out_dir, sections=sections,
                 runs=runs if opts.merge else {**runs, **{s: {'date_utc': time.strftime(
                     '%Y-%m-%dT%H:%M:%SZ', time.gmtime()), 'quick': opts.quick,
                     'fuzz_cases_per_node': opts.fuzz_cases, **load} for s in opts.sections}},
                 method=__doc__)
    return 0


if __name__ == '__main__':
    sys.exit(main())
