"""Benchmark: reliability of the node graph (issue 16) - fuzzing, kill -9 / restart, soak,
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
from typing import Any, Dict, List, Optional, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'tests'))

import numpy as np  # noqa: E402

from stereo_manip_tools.bench_report import goal, results_dir, write_report  # noqa: E402

NAME = 'reliability'
NS = '/reliability'          # the graph's namespace (apart from the fuzz targets' topics)


def _stats(values: List[float]) -> Dict[str, float]:
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=float)
    if not a.size:
        return {'count': 0, 'median': float('nan'), 'p95': float('nan'), 'p99': float('nan'),
                'max': float('nan')}
    return {'count': int(a.size), 'median': float(np.median(a)),
            'p95': float(np.percentile(a, 95)), 'p99': float(np.percentile(a, 99)),
            'max': float(a.max())}


# --- fuzz -----------------------------------------------------------------------------------

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

        @settings(max_examples=10 * cases_per_node, deadline=None, database=None,
                  phases=[Phase.generate], suppress_health_check=list(HealthCheck))
        @given(burst=burst_strategy(target, 5, 15))
        def run(burst):
            if state['cases'] >= cases_per_node:
                return
            r = session.run_cycle(burst)
            results.append(r)
            state['cases'] += r.cases
            if len(results) % 10 == 0:
                log(f'  fuzz {name}: {state["cases"]} cases, {len(results)} bursts, '
                    f'{session.crashes} crashes, '
                    f'{sum(not x.good_ok for x in results)} good inputs missed')
        try:
            run()
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
            'crash_log_tails': [c[-1500:] for c in session.crash_logs[:3]],
            'tracebacks_in_output': output.count('Traceback'),
        }
        log(f'  fuzz {name}: {json.dumps({k: v for k, v in out[name].items() if k not in ("crash_log_tails",)}, default=str)[:600]}')
    return out


# --- the peg_in_hole graph ------------------------------------------------------------------

def graph_specs(rate: float) -> List[Any]:
    from stereo_manip_bringup.demo import _localizer, _stereo, NodeSpec
    cam = NodeSpec('stereo_depth', 'synthetic_camera', 'synthetic_camera',
                   {'scene': 'peg_in_hole', 'rate': rate, 'publish_depth': False,
                    'publish_disparity': False})
    contact = NodeSpec('contact_correction', 'contact_correction_node', 'contact_correction',
                       {'moving_object': 'peg', 'fixed_object': 'hole_block'},
                       {'moving_pose': 'objects/peg/pose',
                        'fixed_pose': 'objects/hole_block/pose',
                        'corrected_pose': 'objects/peg/pose_corrected'})
    return [cam, _stereo(), _localizer('peg_in_hole', ['peg', 'hole_block']), contact]


def _stamp_of_cdr(data: bytes) -> int:
    """Header stamp [ns] of a CDR message that starts with a std_msgs/Header."""
    sec = int.from_bytes(data[4:8], 'little', signed=True)
    nsec = int.from_bytes(data[8:12], 'little')
    return sec * 1_000_000_000 + nsec


class Graph:
    """The graph as processes in namespace NS, and an observer taking raw messages (only the
    stamps are decoded, so watching the 3 MB clouds costs little)."""

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

    def start_node(self, name: str) -> None:
        from stereo_manip_tools.processes import ExecutableProcess
        spec = self.specs[name]
        self.procs[name] = ExecutableProcess(spec.package, spec.executable, (),
                                             spec.ros_args() + ['-r', f'__ns:={NS}'])

    def start(self) -> None:
        for name in self.specs:
            self.start_node(name)
        for name, proc in self.procs.items():
            if not proc.wait_for_node(self.observer, name, 120.0):
                raise RuntimeError(f'{name} did not start:\n{proc.output()[-3000:]}')

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


def _add_s_errors(graph: Graph, stamps: List[int]) -> List[float]:
    """ADD-S [m] of kept corrected poses against the kept truth of the same stamp."""
    from rclpy.serialization import deserialize_message
    from object_localizer.evaluation import add_s
    from object_localizer.localization import prepare_model
    from stereo_manip_tools.conversions import pose_to_matrix
    from stereo_manip_tools.mesh_io import find_model, load_obj
    pts = prepare_model(load_obj(find_model('peg'))).points
    cls = graph.classes['truth']
    truth = {s: d for s, d in graph.kept.get('truth', [])}
    corrected = {s: d for s, d in graph.kept.get('corrected', [])}
    out = []
    for s in stamps:
        if s in truth and s in corrected:
            T = pose_to_matrix(deserialize_message(truth[s], cls).pose)
            C = pose_to_matrix(deserialize_message(corrected[s], cls).pose)
            out.append(float(add_s(C, T, pts)))
    return out


# --- kill / restart -------------------------------------------------------------------------

def run_kill(rate: float, timeout: float, log) -> Dict[str, Any]:
    out: Dict[str, Any] = {}
    graph = Graph(rate, keep_messages=('truth', 'corrected'))
    logs: Dict[str, str] = {}
    try:
        graph.start()
        log('  kill: graph up; waiting for corrected poses')
        if not graph.spin_until(lambda: len(graph.arrivals['corrected']) >= 10, 180.0):
            raise RuntimeError('no corrected poses from the graph:\n' + '\n'.join(
                f'--- {n}\n{p.output()[-1500:]}' for n, p in graph.procs.items()))
        for victim in list(graph.specs):
            graph.spin(5.0)
            before = len(graph.arrivals['corrected'])
            steady = [s for s, _ in graph.arrivals['corrected'][-20:]]
            pids_before = graph.pids()
            kill_wall_ns = time.time_ns()
            t_kill = time.monotonic()
            os.kill(pids_before[victim], signal.SIGKILL)
            graph.procs[victim].process.wait(10.0)
            logs[f'{victim}_killed'] = graph.procs[victim].output()[-3000:]
            graph.start_node(victim)
            t_restart = time.monotonic()

            def resumed() -> bool:
                return any(s > kill_wall_ns for s, _ in graph.arrivals['corrected'][before:])
            ok = graph.spin_until(resumed, timeout)
            t_resume = next((t for s, t in graph.arrivals['corrected'][before:]
                             if s > kill_wall_ns), None)
            graph.spin(3.0)
            after = [s for s, _ in graph.arrivals['corrected'][before:] if s > kill_wall_ns]
            others = {n: graph.procs[n].process.pid == pids_before[n] and graph.procs[n].running()
                      for n in graph.specs if n != victim}
            out[victim] = {
                'resumed': bool(ok),
                'seconds_kill_to_corrected_pose': (t_resume - t_kill) if t_resume else None,
                'seconds_restart_to_corrected_pose': (t_resume - t_restart) if t_resume
                else None,
                'other_nodes_untouched': all(others.values()), 'others': others,
                'corrected_poses_in_3s_after_resume': len(after),
                'add_s_mm_before_kill': _stats([e * 1e3 for e in _add_s_errors(graph, steady)]),
                'add_s_mm_first_10_after': _stats(
                    [e * 1e3 for e in _add_s_errors(graph, after[:10])]),
                'victim_running': graph.procs[victim].running(),
            }
            log(f'  kill {victim}: {json.dumps(out[victim], default=str)[:500]}')
            if not graph.procs[victim].running():
                graph.start_node(victim)
    finally:
        logs.update(graph.stop())
    out['log_tails'] = {k: v[-1200:] for k, v in logs.items()}
    return out


# --- soak -------------------------------------------------------------------------------------

def run_soak(rate: float, minutes: float, warmup_s: float, log) -> Dict[str, Any]:
    graph = Graph(rate)
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
    for name, r in sorted(sections.get('kill', {}).items()):
        if name == 'log_tails':
            continue
        v = r['seconds_kill_to_corrected_pose']
        goals.append(goal(f'kill9_{name}_seconds_to_corrected_pose', 10.0, '<=',
                          v if v is not None else float('nan')))
        goals.append(goal(f'kill9_{name}_other_nodes_restarted', 0, '==',
                          sum(not ok for ok in r['others'].values())))
    soak = sections.get('soak')
    if soak:
        goals.append(goal('soak_nodes_died', 0, '==', len(soak['dead_at_end'])))
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
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--sections', nargs='+', default=['fuzz', 'kill', 'soak', 'recorder'],
                        choices=['fuzz', 'kill', 'soak', 'recorder'])
    parser.add_argument('--fuzz-cases', type=int, default=1000)
    parser.add_argument('--fuzz-nodes', nargs='+', default=None)
    parser.add_argument('--rate', type=float, default=10.0, help='camera rate [Hz]')
    parser.add_argument('--kill-timeout', type=float, default=60.0)
    parser.add_argument('--soak-minutes', type=float, default=10.0)
    parser.add_argument('--warmup', type=float, default=120.0)
    parser.add_argument('--quick', action='store_true',
                        help='smoke run: 30 fuzz cases, 2-minute soak (not a result)')
    parser.add_argument('--out', default=None, help='results directory')
    opts = parser.parse_args(argv)
    if opts.quick:
        opts.fuzz_cases, opts.soak_minutes, opts.warmup = 30, 2.0, 30.0
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    out_dir = Path(opts.out) if opts.out else results_dir()
    path = out_dir / f'{NAME}.json'
    previous = json.loads(path.read_text()) if path.exists() else {}
    sections = previous.get('sections', {})
    load = {'loadavg_start': os.getloadavg()}

    def log(text: str) -> None:
        print(text, flush=True)

    from fuzz_targets import TARGETS
    for section in opts.sections:
        t0 = time.monotonic()
        log(f'== {section}')
        if section == 'fuzz':
            names = opts.fuzz_nodes or sorted(TARGETS)
            result = dict(sections.get('fuzz', {}))
            result.update(run_fuzz(opts.fuzz_cases, names, log))
        elif section == 'kill':
            result = run_kill(opts.rate, opts.kill_timeout, log)
        elif section == 'soak':
            result = run_soak(opts.rate, opts.soak_minutes, opts.warmup, log)
        else:
            result = run_recorder(log)
        sections[section] = result
        load[f'{section}_wall_time_s'] = time.monotonic() - t0
        load[f'loadavg_after_{section}'] = os.getloadavg()
    write_report(NAME, goals_of(sections, 1000), directory=out_dir, sections=sections,
                 runs={**previous.get('runs', {}), **{s: {'date_utc': time.strftime(
                     '%Y-%m-%dT%H:%M:%SZ', time.gmtime()), 'quick': opts.quick,
                     'fuzz_cases_per_node': opts.fuzz_cases, **load} for s in opts.sections}},
                 method=__doc__)
    return 0


if __name__ == '__main__':
    sys.exit(main())
