#!/usr/bin/env python3
"""
The peg_in_hole graph over three machines: rate, latency and link load vs one machine.

Three simulated hosts (Linux network namespaces, ``stereo_manip_tools.netns``) on one LAN:

* camera host: ``synthetic_camera`` free-running at ``--camera-rate`` Hz, 640x480 mono8;
* perception host: ``stereo_depth_node`` + ``object_localizer_node`` + ``contact_correction_node``
  (the demo's nodes and parameters, ``stereo_manip_bringup.demo.STAGES``);
* controller host: a client (``stereo_manip_tools.pose_listener``) that logs every corrected
  peg pose on arrival.

Each host's link is shaped like a NIC of that speed (kernel ``tbf``) and the switch between
them adds the one-way delay and drops a fraction of the frames (``tc netem`` semantics; this
kernel has no ``sch_netem``, so the switch process does it and its own lateness is reported).
The peer in the same run is the one-host graph: the same processes on this machine, localhost
discovery and Fast DDS shared memory.

Every participant on the LAN gets what a user of a multi-host cell gets
(``stereo_manip_bringup.deployment``: SUBNET discovery and the shipped Fast DDS profile
``config/fastdds_multihost.xml``), unless a condition says otherwise: the link conditions of
issue #17 (1 Gbit/s and 100 Mbit/s, 0.5 ms and 5 ms one way, with and without 0.1 % frame
loss), the reduction for a link the image pair does not fit (the stereo node on the camera
host, sending a decimated point cloud instead of the images), and ablations (Fast DDS's
defaults; the profile without its receive buffer; readers answering heartbeats later).

Per condition: corrected-pose rate at the controller, latency = arrival at the controller -
camera stamp (every namespace shares this machine's clock) p50/p90/p95/max, gaps between
poses, the fraction of camera frames that produced a corrected pose, the bytes per second each
host sent over the LAN, IP-reassembly and UDP counters per host, the switch's CPU and
lateness, CPU per node.

Usage (three batches of a few minutes, each with its own one-host peer)::

    ROS_DOMAIN_ID=76 /work/coord/cpu_exclusive .venv/bin/python bench/pipeline_multihost.py \
        --batch 1g          # then --batch 100m, --batch ablations
    python bench/pipeline_multihost.py --seconds 20 --conditions one_host lan_1g_0.5ms

Needs root (network namespaces; without, it says why and exits 0 leaving the results as they
are); writes ``bench/results/pipeline_multihost.json``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import signal
import sys
import tempfile
import time
from typing import Any, Dict, List

from stereo_manip_tools.bench_report import goal, results_dir, write_report
from stereo_manip_tools.netns import list_namespaces, netns_unavailable_reason, VirtualLan

# the link conditions of issue #17: rate [bit/s], one-way delay [s], frame loss
LINKS: Dict[str, Dict[str, float]] = {
    f'lan_{r_name}_{d_name}{l_name}': {'rate': rate, 'delay': delay, 'loss': loss}
    for r_name, rate in (('1g', 1e9), ('100m', 100e6))
    for d_name, delay in (('0.5ms', 0.5e-3), ('5ms', 5e-3))
    for l_name, loss in (('', 0.0), ('_loss0.1', 0.001))}
# name: link, where the stereo node runs, DDS configuration (``dds``: the multi-host profile a
# user gets, ``stereo_manip_bringup/config/fastdds_multihost.xml``, unless said otherwise)
CONDITIONS: Dict[str, Dict[str, Any]] = {'one_host': {'lan': False}}
CONDITIONS.update({name: dict(link) for name, link in LINKS.items()})
CONDITIONS.update({
    # the reduction for a link the image pair does not fit: stereo next to the camera, a
    # cloud of every 4th pixel (~3 mm spacing at 0.45 m = the localiser's voxel) crosses it
    'lan_100m_5ms_loss0.1_stereo_on_camera_decim4': {
        **LINKS['lan_100m_5ms_loss0.1'], 'stereo_on_camera': True,
        'stereo_parameters': {'point_decimation': 4}},
    'lan_100m_0.5ms_stereo_on_camera_decim4': {
        **LINKS['lan_100m_0.5ms'], 'stereo_on_camera': True,
        'stereo_parameters': {'point_decimation': 4}},
    # what a user got before the profile: Fast DDS defaults over UDPv4 (64 kB datagrams that IP
    # fragments, the system's 208 kB socket receive buffer)
    'lan_1g_0.5ms_fastdds_defaults': {**LINKS['lan_1g_0.5ms'], 'dds': 'fastdds_defaults'},
    'lan_1g_5ms_loss0.1_fastdds_defaults': {**LINKS['lan_1g_5ms_loss0.1'],
                                            'dds': 'fastdds_defaults'},
    # the profile without its 4 MB receive buffer = on a host whose net.core.rmem_max was not
    # raised (Linux grants at most rmem_max; the default 208 kB is less than one image)
    'lan_1g_5ms_loss0.1_profile_rcvbuf_default': {**LINKS['lan_1g_5ms_loss0.1'],
                                                  'fastdds_profile': 'max_message_1400'},
    # the profile + readers that answer a heartbeat after 40 ms (Fast DDS: 5 ms): a writer
    # whose history is full (KEEP_LAST 1) piggybacks heartbeats on the fragments while it sends
    # an image; on a slow link the rest of the image is still queued, the reader NACKs it and
    # the writer sends it twice. Waiting longer avoids that, and delays real repairs as much.
    'lan_100m_0.5ms_heartbeat_response_40ms': {**LINKS['lan_100m_0.5ms'],
                                               'fastdds_profile': 'heartbeat_response_40ms'},
    'lan_1g_5ms_loss0.1_heartbeat_response_40ms': {
        **LINKS['lan_1g_5ms_loss0.1'], 'fastdds_profile': 'heartbeat_response_40ms'},
})
# the batches measured in one exclusive-lock run each (a few minutes), each with its own peer
BATCHES = {
    '1g': ['one_host', *[n for n in LINKS if n.startswith('lan_1g')]],
    '100m': ['one_host', *[n for n in LINKS if n.startswith('lan_100m')],
             'lan_100m_5ms_loss0.1_stereo_on_camera_decim4',
             'lan_100m_0.5ms_stereo_on_camera_decim4'],
    'ablations': ['one_host', 'lan_1g_0.5ms_fastdds_defaults',
                  'lan_1g_5ms_loss0.1_fastdds_defaults',
                  'lan_1g_5ms_loss0.1_profile_rcvbuf_default',
                  'lan_100m_0.5ms_heartbeat_response_40ms',
                  'lan_1g_5ms_loss0.1_heartbeat_response_40ms'],
}
IMAGE_PAIR_BYTES = 2 * 640 * 480          # mono8 left + right, payload only


def _shipped_profile_with(block: str) -> str:
    """Return the shipped multi-host profile with ``block`` added after its participant profile."""
    from stereo_manip_bringup.deployment import multihost_profile_path
    text = multihost_profile_path().read_text()
    return text.replace('</participant>', '</participant>\n' + block, 1)


# ablation profiles only: the shipped one is a file of stereo_manip_bringup
FASTDDS_PROFILES = {
    'heartbeat_response_40ms': lambda: _shipped_profile_with("""  <data_reader profile_name="\
stereo_manip_reader" is_default_profile="true">
    <times>
      <heartbeatResponseDelay><sec>0</sec><nanosec>40000000</nanosec></heartbeatResponseDelay>
    </times>
  </data_reader>"""),
    'max_message_1400': """<?xml version="1.0" encoding="UTF-8"?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>udp_mtu</transport_id>
      <type>UDPv4</type>
      <maxMessageSize>1400</maxMessageSize>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="stereo_manip_lan_participant" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>udp_mtu</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
""",
}


def run_condition(name: str, spec: Dict[str, Any], opts: argparse.Namespace,
                  domain: int) -> Dict[str, Any]:
    from stereo_manip_bringup.demo import _model_points
    from stereo_manip_bringup.multihost import HOSTS, peg_in_hole_placement, run_graph, \
        summarise

    placement = peg_in_hole_placement(opts.camera_rate,
                                      stereo_on_camera=spec.get('stereo_on_camera', False),
                                      stereo_parameters=spec.get('stereo_parameters'))
    extra_env: Dict[str, Any] = {}
    if spec.get('fastdds_profile'):
        path = Path(tempfile.gettempdir()) / f'pipeline_multihost_{spec["fastdds_profile"]}.xml'
        text = FASTDDS_PROFILES[spec['fastdds_profile']]
        path.write_text(text() if callable(text) else text)
        extra_env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(path)
    where = {h: [s.node_name for s in specs] for h, specs in placement.items()}
    print(f'== {name}: {spec}', flush=True)
    lan = None
    if spec.get('lan', True):
        lan = VirtualLan(list(HOSTS), rate_bit_s=spec['rate'], delay_s=spec['delay'],
                         loss=spec['loss'], seed=1)
        lan.create()
    try:
        run = run_graph(placement, opts.seconds + opts.warmup + 4.0, domain, lan,
                        log=lambda s: print(s, flush=True), extra_env=extra_env,
                        dds=spec.get('dds', 'multihost_profile'))
    finally:
        if lan is not None:
            left = lan.destroy()
            if left:
                print(f'  WARNING: could not delete namespaces {left}', flush=True)
    result = summarise(run, warmup=opts.warmup, model_points=_model_points('peg'))
    dds = spec.get('dds', 'multihost_profile')
    if spec.get('fastdds_profile'):
        dds = f"ablation profile {spec['fastdds_profile']}"
    result.update(condition=spec, camera_rate_hz_set=opts.camera_rate, batch=opts.batch,
                  dds=dds if lan is not None else 'Fast DDS defaults, shared memory',
                  measured_at=time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                  load_average_after=os.getloadavg(),
                  placement=where if lan is not None else 'all on one host',
                  graph_ready_s=run.ready_s, host_counters_at_end=run.counters,
                  cpu_fraction_of_one_core={k.split('.', 1)[1]: v
                                            for k, v in run.cpu_fraction.items()})
    if lan is not None and result.get('link') and result.get('camera_rate_hz'):
        sent = result['link']['camera']['sent_bytes_per_s']
        result['camera_host_bytes_per_frame'] = sent / result['camera_rate_hz']
        result['link_utilisation_camera_host'] = sent * 8 / spec['rate']
    lat = result.get('latency_ms', {})
    nan = float('nan')
    print(f"  rate {result.get('rate_hz', 0):.2f} Hz, latency p50 {lat.get('p50', nan):.1f}"
          f" p90 {lat.get('p90', nan):.1f} max {lat.get('max', nan):.1f} ms, "
          f"frames with a corrected pose {result.get('frames_with_corrected_pose', 0):.2f}, "
          f"ADD-S p50 {result.get('add_s_corrected_mm', {}).get('p50', nan):.2f} mm",
          flush=True)
    if lan is not None and result.get('link'):
        print('  link Mbit/s sent: ' + ', '.join(
            f"{h} {v['sent_mbit_per_s']:.1f}" for h, v in result['link'].items()), flush=True)
    return result


def _peer(name: str, result: Dict[str, Any]) -> str:
    """Return the one-host run measured in the same batch as ``name``."""
    return f"one_host_{result['batch']}" if result.get('batch') else 'one_host'


def report(results: Dict[str, Any], opts: argparse.Namespace, load_before: Any,
           t0: float, previous: Dict[str, Any]) -> None:
    """Goals from the conditions measured so far; writes the result file."""
    def value(cond: str, *keys: str) -> float:
        v: Any = results.get(cond, {})
        for k in keys:
            v = v.get(k, {}) if isinstance(v, dict) else {}
        return float(v) if isinstance(v, (int, float)) else float('nan')

    goals: List[Dict[str, Any]] = []
    # issue #17: at 1 Gbit/s every camera frame gives a corrected pose at the controller
    # (rate as the one-host benchmark states it: >= 9.9 Hz for a 10.00 Hz camera) within
    # 120 ms p90; on 100 Mbit/s the same for the reduction (stereo next to the camera). NaN
    # (unmet) where not measured.
    goal_conditions = [n for n in LINKS if n.startswith('lan_1g')] + [
        'lan_100m_5ms_loss0.1_stereo_on_camera_decim4',
        'lan_100m_0.5ms_stereo_on_camera_decim4']
    for cond in goal_conditions:
        goals.append(goal(f'{cond}: corrected-pose rate at the controller host [Hz]', 9.9,
                          '>=', value(cond, 'rate_hz')))
        goals.append(goal(f'{cond}: fraction of camera frames with a corrected pose at the '
                          'controller', 1.0, '>=', value(cond, 'frames_with_corrected_pose')))
        goals.append(goal(f'{cond}: latency camera stamp -> controller p90 [ms]', 120.0,
                          '<=', value(cond, 'latency_ms', 'p90')))
    comparison = {}
    for cond, r in results.items():
        peer = _peer(cond, r)
        if cond.startswith('one_host') or 'error' in r or 'error' in results.get(peer, {}):
            continue
        comparison[cond] = {
            'peer': peer,
            'rate_ratio_vs_one_host': value(cond, 'rate_hz') / value(peer, 'rate_hz')
            if value(peer, 'rate_hz') else float('nan'),
            'frames_with_pose_one_host': value(peer, 'frames_with_corrected_pose'),
            'latency_p50_delta_ms': value(cond, 'latency_ms', 'p50')
            - value(peer, 'latency_ms', 'p50'),
            'latency_p90_delta_ms': value(cond, 'latency_ms', 'p90')
            - value(peer, 'latency_ms', 'p90'),
        }
    leftovers = [n for n in list_namespaces() if n.startswith('sm')]
    write_report(
        'pipeline_multihost', goals,
        camera_rate_hz=opts.camera_rate, seconds_per_condition=opts.seconds,
        warmup_s=opts.warmup, image_pair_bytes=IMAGE_PAIR_BYTES,
        image_pair_mbit_s_at_camera_rate=IMAGE_PAIR_BYTES * 8 * opts.camera_rate / 1e6,
        conditions=results, vs_one_host=comparison,
        method=('three network namespaces (camera / perception / controller) on a simulated '
                'LAN: TAP links, kernel tbf rate limit per host egress, a switch process adding '
                'the one-way delay and the frame loss (netem semantics; sch_netem is not in '
                'this kernel); DDS over UDPv4 with SUBNET discovery and, unless a condition '
                'says otherwise, the shipped multi-host Fast DDS profile '
                '(stereo_manip_bringup/config/fastdds_multihost.xml); latency = arrival at the '
                'controller host - camera stamp, one shared clock. Each batch (--batch) is one '
                'exclusive-lock run with its own one-host peer (one_host_<batch>).'),
        namespaces_left_after_run=leftovers,
        notes=('rate_hz = corrected poses arriving in the window / window length; '
               'frames_with_corrected_pose = camera frames (truth poses the controller saw) in '
               'the window that produced a corrected pose; latency and ADD-S are over the poses '
               'that arrived. host_counters_at_end: per host, IP reassembly (ReasmFails, '
               'frag_memory_bytes) and UDP counters (UdpRcvbufErrors: datagrams dropped at a '
               'full socket receive buffer).'),
        previous_run=previous,
        load_average_before=load_before, load_average_after=os.getloadavg(),
        wall_time_s=time.monotonic() - t0)


def _previous_run(old: Dict[str, Any]) -> Dict[str, Any]:
    """
    Return the figures of the last run before the shipped profile.

    The figures of the last run before the shipped profile (kept visible, not re-measured
    under the same names).
    """
    if not old.get('goals'):
        return {}
    keep = ('rate_hz', 'frames_with_corrected_pose', 'latency_ms', 'camera_rate_hz', 'condition')
    return {
        'date': old.get('date'),
        'why_superseded': (
            'measured with Fast DDS defaults over UDPv4 (64 kB datagrams, 208 kB socket '
            'receive buffer) under the same condition names; a user of a multi-host cell now '
            'gets the shipped profile, so the link conditions are re-measured with it, and the '
            'defaults are re-measured as *_fastdds_defaults in the ablations batch. Goals then: '
            '>= 10 Hz and p90 <= 120 ms at 1 Gbit/s.'),
        'goals': old['goals'],
        'conditions': {k: {f: v[f] for f in keep if f in v}
                       for k, v in old.get('conditions', {}).items()}}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--seconds', type=float, default=20.0,
                        help='measured window per condition [s] (after the warm-up)')
    parser.add_argument('--warmup', type=float, default=3.0,
                        help='seconds after the first corrected pose that are not measured')
    parser.add_argument('--camera-rate', type=float, default=10.0, help='camera rate [Hz]')
    parser.add_argument('--batch', choices=list(BATCHES),
                        help='measure this batch of conditions (one_host first, as its peer), '
                             'keeping the other batches of the result file')
    parser.add_argument('--conditions', nargs='+', choices=list(CONDITIONS),
                        help='measure these conditions instead (default: every batch in turn)')
    opts = parser.parse_args()

    def on_term(*_: Any) -> None:
        raise KeyboardInterrupt('SIGTERM')
    # `timeout` sends SIGTERM: unwind like Ctrl-C, so every node is stopped and every namespace
    # of ours deleted on the way out
    signal.signal(signal.SIGTERM, on_term)
    reason = netns_unavailable_reason()
    if reason is not None:
        # like a skipped test: say why, keep the committed results, do not fail `make bench`
        print(f'pipeline_multihost: SKIPPED, cannot simulate hosts here: {reason}',
              file=sys.stderr)
        return 0
    domain = int(os.environ.get('ROS_DOMAIN_ID') or 76)
    load_before = os.getloadavg()
    t0 = time.monotonic()
    results: Dict[str, Any] = {}
    previous_path = results_dir() / 'pipeline_multihost.json'
    old = json.loads(previous_path.read_text()) if previous_path.exists() else {}
    previous = old.get('previous_run') or _previous_run(old)
    if opts.batch or opts.conditions:
        # the other batches' figures stay; figures of the run before the profile (no batch)
        # are in previous_run only
        results = {k: v for k, v in old.get('conditions', {}).items()
                   if v.get('batch') and v.get('batch') != opts.batch}
    plan = ([(opts.batch, BATCHES[opts.batch])] if opts.batch else
            [(None, opts.conditions)] if opts.conditions else list(BATCHES.items()))
    for batch, names in plan:
        opts.batch = batch
        for name in names:
            key = f'one_host_{batch}' if name == 'one_host' and batch else name
            try:
                results[key] = run_condition(name, CONDITIONS[name], opts, domain)
            except RuntimeError as exc:
                print(f'  {name} failed: {str(exc)[:3000]}', flush=True)
                results[key] = {'error': str(exc)[-6000:], 'condition': CONDITIONS[name],
                                'batch': batch}
            report(results, opts, load_before, t0, previous)   # a cut-off run keeps its part
    return 0


if __name__ == '__main__':
    sys.exit(main())
