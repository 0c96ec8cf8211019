"""
The graph across machines: camera host, perception host and controller host over DDS.

Simulated with Linux network namespaces on one machine (stereo_manip_tools.netns): each host
has its own network stack and reaches the others only over a virtual LAN whose switch adds
delay and loss. Skipped, with the reason, where namespaces cannot be made (not root, no
``ip``/``tc``/``/dev/net/tun``, a container refusing them).

Every namespace is named ``sm<random tag>_<host>``; each test removes exactly its own, by name,
also when it fails, and checks that nothing of it is left.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap
import uuid

import numpy as np
import pytest

from stereo_manip_tools.netns import list_namespaces, netns_unavailable_reason, VirtualLan

_REASON = netns_unavailable_reason()
needs_netns = pytest.mark.skipif(_REASON is not None, reason=f'simulated hosts: {_REASON}')


def _own(tag: str):
    return [n for n in list_namespaces() if n.startswith(f'sm{tag}_')]


def _udp_probe(lan: VirtualLan, src: str, dst: str, count: int, gap: float) -> np.ndarray:
    """
    Send ``count`` stamped UDP datagrams src -> dst inside the LAN.

    one-way times [s] of those that arrived (NaN for lost ones). Both ends share this machine's
    clock.
    """
    port = 47000 + os.getpid() % 1000
    receiver = subprocess.Popen(lan.command(dst, [sys.executable, '-c', textwrap.dedent(f"""
        import socket, struct, time
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(('{lan.addresses[dst]}', {port}))
        s.settimeout(30.0)                  # the sender may take a while to start
        print('bound', flush=True)
        got = {{}}
        try:
            while len(got) < {count}:
                data = s.recv(2048)
                s.settimeout(3.0)
                k, t = struct.unpack('!Id', data[:12])
                got[k] = time.time() - t
        except socket.timeout:
            pass
        print(' '.join(f'{{k}}:{{v!r}}' for k, v in got.items()), flush=True)
        """)]), stdout=subprocess.PIPE, text=True)
    try:
        assert receiver.stdout.readline().strip() == 'bound'
        subprocess.run(lan.command(src, [sys.executable, '-c', textwrap.dedent(f"""
            import socket, struct, time
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            for k in range({count}):
                s.sendto(struct.pack('!Id', k, time.time()) + bytes(500),
                         ('{lan.addresses[dst]}', {port}))
                time.sleep({gap})
            """)]), check=True, timeout=60)
        out, _ = receiver.communicate(timeout=30)
    finally:
        if receiver.poll() is None:
            receiver.kill()
            receiver.wait(5)
    times = np.full(count, np.nan)
    for item in out.split():
        k, v = item.split(':')
        times[int(k)] = float(v)
    return times


@pytest.mark.process
@needs_netns
def test_lan_delay_loss_and_cleanup_of_only_its_own_namespaces():
    tag = uuid.uuid4().hex[:6]
    # a namespace that merely looks like ours must survive our clean-up
    decoy = f'sm{tag}_decoy'
    subprocess.run(['ip', 'netns', 'add', decoy], check=True)
    try:
        lan = VirtualLan(['a', 'b'], delay_s=0.020, loss=0.25, tag=tag, seed=3)
        try:
            lan.create()
            assert sorted(_own(tag)) == sorted([decoy, f'sm{tag}_a', f'sm{tag}_b'])
            times = _udp_probe(lan, 'a', 'b', 200, 0.002)
            arrived = times[np.isfinite(times)]
            # 25 % loss: 150 +- 3 sigma (sigma = sqrt(200 * 0.25 * 0.75) = 6.1) arrive
            assert 130 <= arrived.size <= 170, f'{arrived.size} of 200 datagrams arrived'
            # the switch adds 20 ms one way; no datagram may be faster, most not much slower
            assert arrived.min() >= 0.020, f'fastest one-way time {arrived.min() * 1e3:.2f} ms'
            assert np.median(arrived) < 0.040, f'median {np.median(arrived) * 1e3:.1f} ms'
            stats = lan.switch_stats()
            assert stats is not None
            sent = stats['hosts'][f'sm{tag}_a']
            assert sent['lost_frames'] >= 200 - arrived.size - 5
        finally:
            left = lan.destroy()
        assert left == []
        assert _own(tag) == [decoy], 'destroy() must delete its own namespaces, nothing else'
    finally:
        subprocess.run(['ip', 'netns', 'delete', decoy], check=False)
    assert _own(tag) == []


@pytest.mark.process
@needs_netns
def test_failed_creation_removes_what_it_made_and_nothing_else():
    tag = uuid.uuid4().hex[:6]
    clash = f'sm{tag}_second'               # exists already: creating the LAN must fail on it
    subprocess.run(['ip', 'netns', 'add', clash], check=True)
    try:
        lan = VirtualLan(['first', 'second'], tag=tag)
        with pytest.raises(Exception, match='second'):
            lan.create()
        assert _own(tag) == [clash], 'the half-built LAN must be gone, the foreign one kept'
    finally:
        subprocess.run(['ip', 'netns', 'delete', clash], check=False)


def test_lan_rejects_addresses_outside_private_ranges():
    with pytest.raises(ValueError, match='10.0.0.0/8'):
        VirtualLan(['a'], subnet='192.168.1.0/24')


@pytest.mark.process
@needs_netns
def test_peg_in_hole_split_over_three_hosts_reaches_the_controller(tmp_path):
    """
    The peg-in-hole graph split over three hosts reaches the controller.

    Camera host: synthetic camera; perception host: stereo + localizer + contact; controller
    host: a client logging the corrected peg pose. 1 Gbit/s, 0.5 ms links.
    """
    from object_localizer.evaluation import add_s
    from stereo_manip_bringup.multihost import CORRECTED_TOPIC, HOSTS, \
        peg_in_hole_placement, run_graph, TRUTH_TOPIC
    from stereo_manip_bringup.demo import _model_points
    from stereo_manip_tools.transforms import make_transform, matrix_from_quaternion

    tag = uuid.uuid4().hex[:6]
    lan = VirtualLan(list(HOSTS), rate_bit_s=1e9, delay_s=0.5e-3, tag=tag)
    domain = int(os.environ.get('ROS_DOMAIN_ID', '76'))
    try:
        lan.create()
        # the scene played slowly (1 frame per image): the test is about the data crossing the
        # hosts, not about tracking fast motion on a loaded machine
        run = run_graph(peg_in_hole_placement(camera_rate=2.0, frame_step=1), duration=150.0,
                        domain_id=domain, lan=lan, log_dir=tmp_path,
                        stop_after_corrected=4, log=lambda s: None)
    finally:
        assert lan.destroy() == []
    assert _own(tag) == [], 'namespaces left behind'

    corrected = [p for p in run.poses if p['topic'] == CORRECTED_TOPIC]
    truth = {p['stamp_ns']: p for p in run.poses if p['topic'] == TRUTH_TOPIC}
    assert len(corrected) >= 4, (f'{len(corrected)} corrected poses reached the controller '
                                 'host; logs:\n' + '\n'.join(
                                     f'--- {k}\n{v[-1500:]}' for k, v in run.logs.items()))
    # each corrected pose belongs to a camera frame and is right within a few millimetres
    pts = _model_points('peg')

    def matrix(pose):
        return make_transform(matrix_from_quaternion(np.array(pose[3:])), np.array(pose[:3]))
    for p in corrected:
        assert p['stamp_ns'] in truth, 'a corrected pose with a stamp no camera frame had'
        assert p['frame_id'] == 'stereo_left_optical'
        err = add_s(matrix(p['pose']), matrix(truth[p['stamp_ns']]['pose']), pts)
        assert err < 0.005, f'corrected peg pose {err * 1e3:.2f} mm (ADD-S) from the truth'
        latency = (p['arrival_ns'] - p['stamp_ns']) / 1e9
        assert 0 < latency < 60, f'latency {latency} s'
    # the data really crossed the simulated LAN (no shared-memory shortcut between hosts):
    # the camera host sent at least every delivered frame's image pair through the switch,
    # and the controller host received the poses through it
    stats = run.switch_stats
    assert stats is not None
    hosts = {ns.split('_', 1)[1]: h for ns, h in stats['hosts'].items()}
    frames = len(truth)
    assert hosts['camera']['sent_bytes'] >= frames * 2 * 640 * 480, (
        f"camera host sent {hosts['camera']['sent_bytes']} B for {frames} frames")
    assert hosts['controller']['delivered_bytes'] > 0
    assert hosts['perception']['sent_bytes'] > 0
    # the shipped multi-host profile was in force: no datagram larger than one Ethernet frame,
    # so the IP layer of the perception host never had to reassemble the images
    perception = run.counters['perception']
    assert perception['ReasmReqds'] == 0, perception
    assert perception['rx_bytes'] >= frames * 2 * 640 * 480
    assert all(math.isfinite(p['pose'][0]) for p in corrected)


def test_summarise_rate_latency_accuracy_and_link_on_a_known_log():
    """
    The figures the benchmark reports, on a controller log with known answers.

    a pose every 100 ms with 40 ms latency, every 3rd camera frame (30 Hz) corrected, one 10 mm
    error.
    """
    from stereo_manip_bringup.multihost import CORRECTED_TOPIC, GraphRun, summarise, \
        TRUTH_TOPIC

    t_cam = 1_000_000_000_000
    poses, samples = [], []
    identity = [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]
    for k in range(300):                      # 10 s of camera frames at 30 Hz
        stamp = t_cam + k * 33_333_333
        poses.append({'topic': TRUTH_TOPIC, 'stamp_ns': stamp, 'arrival_ns': stamp + 1_000_000,
                      'pose': identity})
        if k % 3 == 0:
            pose = list(identity)
            if k == 150:
                pose[0] += 0.010              # 10 mm off: ADD-S 10 mm for a pure shift
            poses.append({'topic': CORRECTED_TOPIC, 'stamp_ns': stamp,
                          'arrival_ns': stamp + 40_000_000, 'pose': pose})
    for s in range(11):
        samples.append({'wall_ns': t_cam + s * 1_000_000_000, 'seconds': float(s),
                        'cpu_seconds': 0.1 * s, 'lateness_s': {'n': 1, 'p50': 1e-4},
                        'hosts': {'smx_camera': {'sent_bytes': s * 6_000_000, 'lost_frames': 0,
                                                 'sent_frames': s * 4000,
                                                 'delivered_bytes': 0}}})
    run = GraphRun(poses, {}, t_cam, t_cam + 10_000_000_000, switch_samples=samples)
    model = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])   # far apart
    out = summarise(run, warmup=2.0, model_points=model)
    assert out['rate_hz'] == pytest.approx(10.0, rel=0.02)
    assert out['latency_ms']['p50'] == pytest.approx(40.0, abs=1e-6)
    assert out['latency_ms']['max'] == pytest.approx(40.0, abs=1e-6)
    assert out['frames_with_corrected_pose'] == pytest.approx(1 / 3, abs=0.02)
    assert out['camera_rate_hz'] == pytest.approx(30.0, rel=0.05)
    assert out['add_s_corrected_mm']['max'] == pytest.approx(10.0, abs=1e-6)
    assert out['add_s_corrected_mm']['p50'] == pytest.approx(0.0, abs=1e-9)
    assert out['link']['camera']['sent_mbit_per_s'] == pytest.approx(48.0, rel=1e-6)
    assert out['switch_cpu_fraction'] == pytest.approx(0.1, rel=1e-6)
    # a stream that stops half-way is counted over the whole window, not over its burst
    run.poses = [p for p in poses if p['topic'] != CORRECTED_TOPIC
                 or p['stamp_ns'] < t_cam + 6_000_000_000]
    stopped = summarise(run, warmup=2.0)
    assert stopped['rate_hz'] == pytest.approx(10.0 * 4 / 8, rel=0.05)
    assert stopped['last_corrected_before_end_s'] == pytest.approx(4.0, abs=0.2)


def test_multihost_environment_names_the_shipped_profile():
    """
    What ``multihost:=true`` and ``python -m stereo_manip_bringup.deployment`` give.

    SUBNET discovery and a Fast DDS profile whose UDP datagrams fit one Ethernet frame, with a
    receive buffer larger than one image pair.
    """
    import xml.etree.ElementTree as ET
    from stereo_manip_bringup.deployment import multihost_environment

    env = multihost_environment(domain_id=42)
    assert env['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET' and env['ROS_DOMAIN_ID'] == '42'
    ns = {'f': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(env['FASTRTPS_DEFAULT_PROFILES_FILE']).getroot()
    transport = root.find('f:transport_descriptors/f:transport_descriptor', ns)
    assert transport.find('f:type', ns).text == 'UDPv4'
    assert int(transport.find('f:maxMessageSize', ns).text) <= 1500 - 20 - 8   # IP + UDP
    assert int(transport.find('f:receiveBufferSize', ns).text) > 2 * 640 * 480
    participant = root.find('f:participant', ns)
    assert participant.get('is_default_profile') == 'true'
    assert participant.find('f:rtps/f:useBuiltinTransports', ns).text == 'false'
    used = participant.find('f:rtps/f:userTransports/f:transport_id', ns).text
    assert used == transport.find('f:transport_id', ns).text


def test_deployment_prints_export_lines(capsys):
    from stereo_manip_bringup.deployment import main
    assert main(['--domain-id', '7']) == 0
    lines = capsys.readouterr().out.splitlines()
    assert 'export ROS_DOMAIN_ID=7' in lines
    assert any(line.startswith('export FASTRTPS_DEFAULT_PROFILES_FILE=') and
               line.endswith('fastdds_multihost.xml') for line in lines)
