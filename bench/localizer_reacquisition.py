#!/usr/bin/env python3
"""
Losses and re-acquisition of the localiser node on a slow graph, in-process, against truth.

The ``revolute_pair`` scene (link_base and link_arm: two identical bricks, hinted with their
frame-0 poses as the demo does) as the graph's stereo node sees it (the clouds of
``bench/localizer_graph_cpu.py``, cached), every ``--step``-th scene frame (default 18: the
0.6 s between the clouds a loaded free-running graph processes, see
``bench/results/localizer_live.json``; the scene loops, so its last-to-first frame is a real
28 mm jump of both links), stamps ``step / 30`` s apart, fed to an in-process
``ObjectLocalizerNode`` through its per-cloud method.

Per object and cloud: the published pose's ADD-S against the truth, the status reason, the
tracker's CPU. A loss is a cloud whose outcome says the track was lost; its re-acquisition CPU
is the object's tracker CPU from that cloud to the next cloud with a verified pose (inclusive).

Peer, in the same run on the same clouds: the node with the local re-acquisition off
(``relock_window`` 0: every loss goes to the global search, as before the re-lock) and the
naming radius fixed (``twin_max_speed`` 0: 20 mm), the global searches uncapped
(``search_cpu_share`` 1).

Usage: ``ROS_DOMAIN_ID=57 nice -n 10 python bench/localizer_reacquisition.py [--clouds 60]``.
Writes ``bench/results/localizer_reacquisition.json``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time
from typing import Any, Dict, List

from stereo_manip_tools.bench_report import goal, write_report

# its own cache of the stereo clouds: the default one of localizer_graph_cpu.py may hold clouds
# of an older stereo node (a flat surface at the band limit, which the node now leaves unknown)
os.environ.setdefault('LOCALIZER_GRAPH_CACHE', '/tmp/localizer_reacquisition_cache')
sys.path.insert(0, str(Path(__file__).resolve().parent))   # localizer_graph_cpu

PEER = {'relock_window': 0.0, 'twin_max_speed': 0.0, 'search_cpu_share': 1.0}


def frames_of(step: int, count: int, n_scene: int = 300) -> List[int]:
    """Scene frames of ``count`` processed clouds ``step`` apart, looping (multiples of 3)."""
    return [(k * step) % n_scene // 3 * 3 for k in range(count)]


def run(data: List[Dict[str, Any]], step: int, overrides: Dict[str, Any]) -> Dict[str, Any]:
    """Feed the clouds to a fresh in-process node with ``overrides``; score every outcome."""
    from rclpy.parameter import Parameter

    from localizer_graph_cpu import spread
    from object_localizer.evaluation import add_s
    from object_localizer.localizer_node import ObjectLocalizerNode
    from stereo_manip_bringup.demo import _localizer
    from stereo_manip_tools.conversions import xyz_to_pointcloud2

    spec = _localizer('revolute_pair', ['link_base', 'link_arm'])
    params = {**spec.parameters, **overrides}
    node = ObjectLocalizerNode(parameter_overrides=[Parameter(k, value=v)
                                                    for k, v in params.items()])
    outcomes: Dict[str, list] = {n: [] for n in node.trackers}
    original = node._publish

    def publish(name, result, *a):
        outcomes[name].append(result)
        original(name, result, *a)
    node._publish = publish
    dt_ns = int(step / 30.0 * 1e9)
    cpu, load0 = [], os.getloadavg()
    for i, d in enumerate(data):
        msg = xyz_to_pointcloud2(d['points'])
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(1_000_000_000 + i * dt_ns,
                                                                1_000_000_000)
        msg.header.frame_id = 'left_camera_optical_frame'
        c0 = time.process_time()
        node._process(msg)
        cpu.append(time.process_time() - c0)
    load1 = os.getloadavg()
    objects = {}
    for name, tracker in node.trackers.items():
        errs, recov, lost_cpu, unrecovered, ambiguous, deferred, rows = [], [], None, 0, 0, 0, []
        for i, r in enumerate(outcomes[name]):
            e = None if r.pose is None else add_s(r.pose, data[i]['poses'][name],
                                                  tracker.model.points)
            if e is not None:
                errs.append(e)
            ambiguous += 'ambiguous' in r.reason or 'not clearly nearer' in r.reason
            deferred += 'global search deferred' in r.reason
            if r.lost and lost_cpu is None:
                lost_cpu = 0.0
            if lost_cpu is not None:
                lost_cpu += r.cpu_seconds
                if r.pose is not None:
                    recov.append(lost_cpu)
                    lost_cpu = None
            rows.append({'frame': data[i]['k'], 'add_s_mm': None if e is None else 1e3 * e,
                         'lost': r.lost, 'cpu_s': r.cpu_seconds, 'reason': r.reason[:300]})
        unrecovered = int(lost_cpu is not None)
        objects[name] = {
            'published': len(errs), 'clouds': len(outcomes[name]),
            'add_s_mm': spread([1e3 * e for e in errs]),
            'published_over_5mm': int(sum(e > 0.005 for e in errs)),
            'losses': int(sum(r.lost for r in outcomes[name])),
            'recoveries': len(recov), 'unrecovered_at_end': unrecovered,
            'reacquisition_cpu_s': spread(recov), 'reacquisition_cpu_s_all': recov,
            'clouds_ambiguous': int(ambiguous), 'clouds_search_deferred': int(deferred),
            'per_cloud': rows}
    node.destroy_node()
    return {'overrides': overrides, 'cpu_ms_per_cloud': spread([1e3 * c for c in cpu]),
            'objects': objects, 'load_average': {'start': load0, 'end': load1}}


def main() -> None:
    """Run the peer and the node on the same clouds; write the report."""
    parser = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    parser.add_argument('--step', type=int, default=18, help='scene frames between clouds')
    parser.add_argument('--clouds', type=int, default=60)
    args = parser.parse_args()
    import rclpy

    from localizer_graph_cpu import spread, stereo_clouds
    rclpy.init()
    data = stereo_clouds('revolute_pair', frames_of(args.step, args.clouds))
    runs = {}
    for label, overrides in (('peer: local re-acquisition off', PEER), ('now', {})):
        runs[label] = run(data, args.step, overrides)
        for name, o in runs[label]['objects'].items():
            print(f"{label} {name}: published {o['published']}/{o['clouds']}, over 5 mm "
                  f"{o['published_over_5mm']}, losses {o['losses']}, unrecovered "
                  f"{o['unrecovered_at_end']}, re-acq CPU s {o['reacquisition_cpu_s']}, "
                  f"ambiguous {o['clouds_ambiguous']}", flush=True)
    rclpy.shutdown()
    now = runs['now']['objects'].values()
    recov = [x for o in now for x in o['reacquisition_cpu_s_all']]
    unrec = sum(o['unrecovered_at_end'] for o in now)
    goals = [
        goal('published_poses_over_5mm_add_s', 0, '==',
             sum(o['published_over_5mm'] for o in now)),
        goal('losses_not_reacquired', 0, '==', unrec),
        goal('reacquisition_cpu_s_max', 1.0, '<=',
             max(recov) if recov and not unrec else float('nan')),
        goal('clouds_without_pose_share', 0.1, '<=',
             sum(o['clouds'] - o['published'] for o in now)
             / max(sum(o['clouds'] for o in now), 1)),
    ]
    write_report('localizer_reacquisition', goals, runs=runs, args=vars(args),
                 reacquisition_cpu_s=spread(recov),
                 peer_reacquisition_cpu_s=spread(
                     [x for o in runs['peer: local re-acquisition off']['objects'].values()
                      for x in o['reacquisition_cpu_s_all']]))


if __name__ == '__main__':
    main()
