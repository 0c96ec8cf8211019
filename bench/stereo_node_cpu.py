#!/usr/bin/env python3
"""
CPU per frame of ``stereo_depth_node`` at 640x480 in the live configuration, split by stage.

1. The node as its own process, with the parameters of the free-running peg_in_hole graph
   (``stereo_manip_bringup.demo``: band 48-159 px = 112 disparities, ``point_decimation`` 2,
   reliable input, ``LIVE_PARAMETERS``: one numba thread), fed pre-rendered ``peg_in_hole``
   pairs (mono8 + CameraInfo) in lock-step: the next pair is published when the cloud of the
   previous one has arrived, so no pair is dropped and every frame is measured. Only
   ``points2`` is subscribed, as in the graph. CPU per frame = the node process's CPU time
   (sum of ``/proc/<pid>/task/*/schedstat`` run times, ns resolution) from one publication to
   the next: everything the process does for a frame (DDS receive, decoding, matching, cloud,
   serialisation, executor), robust to the load of other processes.
2. In this process, one numba thread (``NUMBA_NUM_THREADS=1`` is set before numba loads), the
   node's per-frame work split by stage with ``time.process_time``: decoding, census transforms,
   fused cost + aggregation + WTA, left-right check, speckle filter, median, fill, depth, cloud
   points, PointCloud2 packing; and the cloud path that main used
   (``pipeline.cloud_points`` + ``conversions.xyz_to_pointcloud2``) measured on the same frames
   as the peer of the packed cloud (``pipeline.cloud_message_data``).

1b. The same lock-step run with the node under ``bench/stereo_node_profiled.py``: its own
   ``main()`` with the per-frame functions wrapped, process and thread CPU per call of every
   stage inside the node process (``node_process_profiled.stages``): where the node's CPU goes,
   DDS, executor and the copies around the kernels included.

3. Main's per-frame path against this branch's, alternated frame by frame in this process
   (``paired_main_vs_branch``): the change measured under one and the same load. The peer is
   the path of 7594e47 (its kernel and median copied here, OpenCV's ``filterSpeckles``).

4. With ``--baseline-tree DIR`` (a built checkout, e.g. the main branch): that tree's node and
   this tree's, as separate processes like part 1, run alternately ``--rounds`` times each
   (``node_process_before_after``): a change of the node process measured under the same load.
   Part 1 also counts the node's minor page faults per frame (a freed array unmapped by glibc
   is faulted in again by the next frame).

Goals: node process CPU per frame median <= 50 ms (half a core at 10 Hz: the localiser and
the contact node need the rest of the two cores); cloud build + pack p95 <= 10 ms.

Run: ``python bench/stereo_node_cpu.py [--frames N] [--baseline-tree DIR --rounds R]``; writes
``bench/results/stereo_node_cpu.json``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import random  # noqa: I100
import time
from typing import Any, Callable, Dict, List

os.environ.setdefault('NUMBA_NUM_THREADS', '1')
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
os.environ.setdefault('ROS_DOMAIN_ID', str(random.randint(1, 100)))

import numpy as np  # noqa: E402

from stereo_manip_tools.bench_report import goal, write_report  # noqa: E402

SCENE = 'peg_in_hole'


def _main_kernel():
    """Return main's fused kernel and 3x3 median (the peers), compiled on first call."""
    import numba

    from stereo_depth.matching_cost import _hamming_row, _reverse_row
    from stereo_depth.optimization import _right_row, _wta_pixel

    @numba.njit(parallel=True, nogil=True, fastmath=True, boundscheck=False)
    def _main_census_box_wta(cl, cr, nd, rw, rh, invalid, nchunks, uniqueness):
        # main's fused kernel (7594e47, copied unchanged), the peer of the paired comparison:
        # census-Hamming cost -> box sum (borders replicated) -> WTA of both views, row by
        # row, 32-bit codes, uint8 Hamming rows, per-pixel WTA with a right-view argmin.
        h, w = cl.shape
        dl = np.empty((h, w), np.float32)
        dr = np.empty((h, w), np.float32)
        for ci in numba.prange(nchunks):
            y0 = ci * h // nchunks
            y1 = (ci + 1) * h // nchunks
            if y0 >= y1:
                continue
            vs = np.zeros((w, nd), np.uint16)
            # ring of Hamming rows: row r lives in slot r % nring until it leaves the window
            nring = 2 * rh + 2
            ring = np.empty((nring, w, nd), np.uint8)
            crr = np.empty(w, cr.dtype)
            hs = np.zeros(nd, np.uint16)
            rmin = np.empty(w, np.uint16)
            rarg = np.empty(w, np.int32)
            for r in range(max(y0 - rh, 0), min(y0 + rh, h - 1) + 1):
                _reverse_row(cr[r], crr)
                _hamming_row(cl[r], crr, nd, invalid, ring[r % nring])
            for dy in range(-rh, rh + 1):
                hadd = ring[min(max(y0 + dy, 0), h - 1) % nring]
                for x in range(w):
                    vrow = vs[x]
                    arow = hadd[x]
                    for d in range(nd):
                        vrow[d] = np.uint16(vrow[d] + arow[d])
            for y in range(y0, y1):
                if y > y0:
                    ya = min(y + rh, h - 1)
                    ys = max(y - rh - 1, 0)
                    if ya != ys:
                        if y + rh <= h - 1:
                            _reverse_row(cr[ya], crr)
                            _hamming_row(cl[ya], crr, nd, invalid, ring[ya % nring])
                        hadd = ring[ya % nring]
                        hsub = ring[ys % nring]
                        for x in range(w):
                            vrow = vs[x]
                            arow = hadd[x]
                            srow = hsub[x]
                            for d in range(nd):
                                vrow[d] = np.uint16(vrow[d] + arow[d] - srow[d])
                rmin[:] = np.uint16(65535)
                rarg[:] = -1
                hs[:] = 0
                for dx in range(-rw, rw + 1):
                    vrow = vs[min(max(dx, 0), w - 1)]
                    for d in range(nd):
                        hs[d] = np.uint16(hs[d] + vrow[d])
                dl[y, 0] = _wta_pixel(hs, 0, w, rmin, rarg, uniqueness, nd <= 256)
                for x in range(1, w):
                    va = vs[min(x + rw, w - 1)]
                    vb = vs[max(x - rw - 1, 0)]
                    for d in range(nd):
                        hs[d] = np.uint16(hs[d] + va[d] - vb[d])
                    dl[y, x] = _wta_pixel(hs, x, w, rmin, rarg, uniqueness, nd <= 256)
                _right_row(rarg, dr[y])
        return dl, dr

    # main's 3x3 median (7594e47, copied unchanged): OpenCV's median of the complete windows,
    # the valid-neighbour median elsewhere
    @numba.njit(parallel=True, nogil=True)
    def _main_nan_median(d, r, full, use_full):
        # full: the plain median of every complete window (OpenCV), used where the whole window
        # lies inside the image and holds no NaN; other pixels take the median of their valid
        # neighbours by insertion sort.
        h, w = d.shape
        out = np.empty_like(d)
        for y in numba.prange(h):
            buf = np.empty((2 * r + 1) * (2 * r + 1), np.float32)
            inner_y = r <= y < h - r
            for x in range(w):
                if np.isnan(d[y, x]):
                    out[y, x] = np.nan
                    continue
                if use_full and inner_y and r <= x < w - r:
                    s = np.float32(0.0)
                    for yy in range(y - r, y + r + 1):
                        for xx in range(x - r, x + r + 1):
                            s += d[yy, xx]
                    if not np.isnan(s):     # NaN propagates through the sum
                        out[y, x] = full[y, x]
                        continue
                n = 0
                for yy in range(max(0, y - r), min(h, y + r + 1)):
                    for xx in range(max(0, x - r), min(w, x + r + 1)):
                        v = d[yy, xx]
                        if not np.isnan(v):
                            # insertion into the sorted prefix buf[:n]
                            k = n
                            while k > 0 and buf[k - 1] > v:
                                buf[k] = buf[k - 1]
                                k -= 1
                            buf[k] = v
                            n += 1
                out[y, x] = buf[n // 2] if n % 2 == 1 else 0.5 * (buf[n // 2 - 1] + buf[n // 2])
        return out

    return _main_census_box_wta, _main_nan_median


def opencv_speckles(disparity: np.ndarray, max_size: int, max_diff: float) -> np.ndarray:
    """Main's speckle filter (the peer): OpenCV's ``filterSpeckles`` on the 1/16 px int16."""
    import cv2
    d = np.asarray(disparity, dtype=np.float32)
    fixed = np.where(np.isnan(d), -1.0, np.round(d * 16.0)).astype(np.int16)
    cv2.filterSpeckles(fixed, -1, int(max_size), int(round(max_diff * 16.0)))
    out = d.copy()
    out[fixed == -1] = np.nan
    return out


def stats(values: List[float]) -> Dict[str, float]:
    """Return median, p95, max and n of ``values``."""
    a = np.asarray(values, float)
    return {'median': float(np.median(a)), 'p95': float(np.percentile(a, 95)),
            'max': float(a.max()), 'n': int(a.size)}


def node_parameters() -> Dict[str, Any]:
    """Return the stereo node's parameters in the free-running peg_in_hole graph."""
    from stereo_manip_bringup.demo import LIVE_PARAMETERS, STAGES
    for spec in STAGES[SCENE]().nodes:
        if spec.executable == 'stereo_depth_node':
            # lock-step feeding publishes the next pair as soon as the last cloud is back (stamps
            # ~60 ms apart): the graph's max_rate would skip it; every pair is measured here
            return {**spec.parameters, **LIVE_PARAMETERS.get('stereo_depth_node', {}),
                    'max_rate': 0.0}
    raise RuntimeError(f'no stereo node in the {SCENE} graph')


def render_frames(n: int):
    """``n`` pairs of the scene (every 3rd frame, as the 10 Hz camera), with camera infos."""
    from std_msgs.msg import Header

    from stereo_depth.synthetic import render
    from stereo_depth.synthetic.camera import StereoCamera
    from stereo_manip_tools.conversions import camera_info_from_parameters, numpy_to_image, \
        StereoCameraParameters

    c = StereoCamera.create()
    params = StereoCameraParameters(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy, baseline=c.baseline,
                                    width=c.width, height=c.height)
    frames = []
    for k in range(n):
        left, right, _ = render(SCENE, 3 * k)
        h = Header(frame_id='camera_optical_frame')
        frames.append((numpy_to_image(left, 'mono8', h), numpy_to_image(right, 'mono8', h)))
    infos = camera_info_from_parameters(params, Header(frame_id='camera_optical_frame'))
    return frames, infos


def task_cpu_ns(pid: int) -> int:
    """Run time [ns] of all threads of ``pid`` (``/proc/<pid>/task/*/schedstat``)."""
    total = 0
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            total += int((task / 'schedstat').read_text().split()[0])
        except (OSError, IndexError, ValueError):
            pass
    return total


def minor_faults(pid: int) -> int:
    """Minor page faults of ``pid`` so far (``/proc/<pid>/stat`` field 10)."""
    return int(Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[7])


def task_cpu_by_thread(pid: int) -> Dict[str, int]:
    """Run time [ns] of each thread of ``pid``, keyed ``'<name>/<tid>'``."""
    out = {}
    for task in Path(f'/proc/{pid}/task').iterdir():
        try:
            name = (task / 'comm').read_text().strip()
            out[f'{name}/{task.name}'] = int((task / 'schedstat').read_text().split()[0])
        except (OSError, IndexError, ValueError):
            pass
    return out


def node_process(frames, infos, params: Dict[str, Any], warmup: int = 3,
                 profile_out: str = '', python_path: str = '') -> Dict[str, Any]:
    """
    CPU per frame of the node process in lock-step (part 1 of the module docstring).

    With ``profile_out`` the node runs under ``bench/stereo_node_profiled.py`` (part 1b): the
    stage split is read from that file and returned as ``stages``. ``python_path`` is put in
    front of the node's ``PYTHONPATH`` (part 4: another tree's packages). The per-frame values
    are returned under ``cpu_ms_per_frame_values``.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from stereo_manip_tools.conversions import ns_to_stamp, stamp_to_ns
    from stereo_manip_tools.processes import ExecutableProcess, make_node, shutdown_node, \
        spin_until

    ros_args = []
    for k, v in params.items():
        ros_args += ['-p', f'{k}:={str(v).lower() if isinstance(v, bool) else v}']
    node = make_node(f'bench_stereo_cpu_{os.getpid()}')
    qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {n: node.create_publisher(t, n, qos) for n, t in (
        ('left/image_rect', Image), ('right/image_rect', Image),
        ('left/camera_info', CameraInfo), ('right/camera_info', CameraInfo))}
    got: Dict[int, int] = {}
    node.create_subscription(PointCloud2, 'points2',
                             lambda m: got.__setitem__(stamp_to_ns(m.header.stamp), m.width),
                             QoSProfile(depth=1))
    if profile_out:
        proc = _ProfiledNode(ros_args, {'NUMBA_NUM_THREADS': '1',
                                        'STEREO_PROFILE_OUT': profile_out})
    else:
        env = {'NUMBA_NUM_THREADS': '1'}
        if python_path:
            env['PYTHONPATH'] = os.pathsep.join(
                [python_path] + ([os.environ['PYTHONPATH']] if os.environ.get('PYTHONPATH')
                                 else []))
        proc = ExecutableProcess('stereo_depth', 'stereo_depth_node', ros_args=ros_args,
                                 env=env)
    try:
        if not proc.wait_for_output('warm-up', timeout=120.0):
            raise RuntimeError('stereo node did not start:\n' + proc.output()[-2000:])
        spin_until(node, lambda: pubs['left/image_rect'].get_subscription_count() > 0
                   and node.count_subscribers('points2') > 0, 20.0)
        pid = proc.process.pid
        cpu_ms: List[float] = []
        latency_ms: List[float] = []
        points: List[int] = []
        lost = 0
        t_start = time.monotonic()
        c_start = None
        for i, (lm, rm) in enumerate([frames[0]] * warmup + list(frames)):
            stamp_ns = time.time_ns()
            stamp = ns_to_stamp(stamp_ns)
            for m in (lm, rm, *infos):
                m.header.stamp = stamp
            c0 = task_cpu_ns(pid)
            if i == warmup:
                c_start, t_start = c0, time.monotonic()
                threads_start = task_cpu_by_thread(pid)
                faults_start = minor_faults(pid)
            pubs['left/camera_info'].publish(infos[0])
            pubs['right/camera_info'].publish(infos[1])
            pubs['left/image_rect'].publish(lm)
            pubs['right/image_rect'].publish(rm)
            ok = spin_until(node, lambda: stamp_ns in got, 5.0)
            t_recv = time.time_ns()
            spin_until(node, lambda: False, 0.02)      # let the node settle (idle spin)
            if i < warmup:
                continue
            cpu_ms.append((task_cpu_ns(pid) - c0) / 1e6)
            if ok:
                latency_ms.append((t_recv - stamp_ns) / 1e6)
                points.append(got[stamp_ns])
            else:
                lost += 1
        c_end = task_cpu_ns(pid)
        threads_end = task_cpu_by_thread(pid)
        faults_end = minor_faults(pid)
        window = time.monotonic() - t_start
        log = proc.output()
    finally:
        proc.stop()
        shutdown_node(node)
    n = len(frames)
    stages = None
    if profile_out:
        import json
        stages = json.loads(Path(profile_out).read_text())
    by_name: Dict[str, float] = {}
    for key, ns in threads_end.items():
        name = key.rsplit('/', 1)[0]
        by_name[name] = by_name.get(name, 0.0) + (ns - threads_start.get(key, 0)) / 1e6 / n
    by_tid = {key: (ns - threads_start.get(key, 0)) / 1e6 / n for key, ns in threads_end.items()}
    return {'cpu_ms_per_frame_by_thread_name': {k: v for k, v in sorted(
                by_name.items(), key=lambda kv: -kv[1]) if v > 0.01},
            'cpu_ms_per_frame_by_thread': {k: v for k, v in sorted(
                by_tid.items(), key=lambda kv: -kv[1]) if v > 0.01},
            'parameters': params, 'frames': n, 'clouds_lost': lost,
            'cpu_ms_per_frame': stats(cpu_ms), 'cpu_ms_per_frame_values': cpu_ms,
            'cpu_ms_per_frame_mean_over_window': (c_end - c_start) / 1e6 / n,
            'window_s': window,
            'minor_page_faults_per_frame_mean': (faults_end - faults_start) / n,
            'cloud_latency_ms_lockstep': stats(latency_ms) if latency_ms else None,
            'points_per_cloud': stats(points) if points else None,
            'node_log_tail': log[-1500:], **({'stages': stages} if stages else {})}


class _ProfiledNode:
    """``bench/stereo_node_profiled.py`` as a process, with ExecutableProcess's interface."""

    def __init__(self, ros_args: List[str], env: Dict[str, str]) -> None:
        import subprocess
        import sys
        import tempfile
        from stereo_manip_tools.processes import interrupt_then_kill
        self._stop = interrupt_then_kill
        self._log = tempfile.NamedTemporaryFile(prefix='stereo_profiled_', suffix='.log',
                                                delete=False)
        self.process = subprocess.Popen(
            [sys.executable, str(Path(__file__).with_name('stereo_node_profiled.py')),
             '--ros-args', *ros_args], stdout=self._log, stderr=subprocess.STDOUT,
            env={**os.environ, 'PYTHONUNBUFFERED': '1', **env})

    def output(self) -> str:
        """Everything the process printed so far."""
        self._log.flush()
        return Path(self._log.name).read_text(errors='replace')

    def wait_for_output(self, text: str, timeout: float) -> bool:
        """Wait until ``text`` appears in the output or the process exits."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if self.process.poll() is not None:
                return text in self.output()
            time.sleep(0.05)
        return False

    def stop(self) -> int:
        """SIGINT, then SIGKILL (the profile is written at the interpreter's exit)."""
        return self._stop(self.process, 10.0)


def stage_split(frames, infos, params: Dict[str, Any]) -> Dict[str, Any]:
    """Per-stage CPU per frame in this process (part 2 of the module docstring)."""
    import numba

    from stereo_depth import matching_cost as mc, optimization as op, pipeline as pl, \
        refinement as rf
    from stereo_depth.stereo_depth_node import prepare_pair, stereo_geometry
    from stereo_manip_tools.conversions import xyz_to_pointcloud2

    numba.set_num_threads(1)
    dmin, nd = int(params['min_disparity']), int(params['max_disparity'])
    dec = int(params['point_decimation'])
    defaults = pl.method_defaults('block_matching')
    cw, win = tuple(defaults['census_window']), tuple(defaults['window'])
    nbits = np.uint8(cw[0] * cw[1] - 1)
    times: Dict[str, List[float]] = {}

    def timed(name: str, f: Callable, *a, **k):
        c0 = time.process_time()
        out = f(*a, **k)
        times.setdefault(name, []).append(1e3 * (time.process_time() - c0))
        return out

    same_xyz = True
    same_speckles = True
    for rep, (lm, rm) in enumerate([frames[0], frames[1]] + list(frames)):
        if rep == 2:
            times.clear()
        limg, rimg, colours = timed('decode images', prepare_pair, lm, rm)
        h, w = limg.shape
        geo = stereo_geometry(infos[0], infos[1], w, h)
        lc = np.ascontiguousarray(limg[:, dmin:])
        rc = np.ascontiguousarray(rimg[:, :w - dmin])
        cl = timed('census byte planes, left', mc.census_planes, lc, cw)
        cr = timed('census byte planes, right', mc.census_planes, rc, cw)
        dl, dr = timed('cost + aggregation + WTA (fused)', op._census_box_wta, cl, cr, nd,
                       win[0] // 2, win[1] // 2, nbits, 1, 0.0)
        d = timed('left-right check', rf.left_right_check, dl, dr, defaults['lr_max_diff'])
        ds = timed('peer: speckle filter (OpenCV filterSpeckles, main)', opencv_speckles, d,
                   defaults['speckle_size'], defaults['speckle_diff'])
        d = timed('speckle filter', rf.remove_speckles, d, defaults['speckle_size'],
                  defaults['speckle_diff'])
        same_speckles &= bool(np.array_equal(d, ds, equal_nan=True))
        d = timed('median filter', rf.median_filter, d, defaults['median'])
        d = timed('fill', rf.fill_invalid, d, 'row')
        disp = timed('compute_disparity (all of the above but decoding)', pl.compute_disparity,
                     limg, rimg, 'block_matching', nd, min_disparity=dmin)
        depth = timed('depth', pl.disparity_to_depth, disp, geo['fx'], geo['baseline'],
                      geo['doffs'])
        data = timed('cloud build + pack (packed, this branch)', pl.cloud_message_data, depth,
                     geo['fx'], geo['fy'], geo['cx'], geo['cy'], dec, False, colours)
        pts, rgb = timed('peer: cloud_points (main)', pl.cloud_points, depth, geo['fx'],
                         geo['fy'], geo['cx'], geo['cy'], dec, False, colours)
        msg = timed('peer: xyz_to_pointcloud2 (main)', xyz_to_pointcloud2, pts, lm.header)
        same_xyz &= bytes(msg.data) == data.buffer.tobytes()
    peer = [a + b for a, b in zip(times['peer: cloud_points (main)'],
                                  times['peer: xyz_to_pointcloud2 (main)'])]
    out = {k: stats(v) for k, v in times.items()}
    out['peer: cloud build + pack (main)'] = stats(peer)
    return {'cpu_ms': out, 'packed_bytes_identical_to_main': bool(same_xyz),
            'speckle_filter_identical_to_opencv': bool(same_speckles),
            'numba_threads': int(numba.get_num_threads())}


def paired_main_vs_branch(frames, infos, params: Dict[str, Any],
                          rounds: int = 2) -> Dict[str, Any]:
    """
    CPU per frame of main's per-frame path and of this branch's, alternated frame by frame.

    The shared machine's load moves CPU times by +-15 ms between runs a minute apart (the
    node-process figures of part 1 cannot separate a 10 ms change); alternating the two paths
    on every frame gives both the same load, and the per-frame difference is the change.
    main's path (7594e47): 32-bit census codes (``census_transform``) into main's fused kernel
    (``_main_kernel``: uint8 Hamming rows, per-pixel WTA), main's median (OpenCV + the
    valid-neighbour median), OpenCV's ``filterSpeckles`` (``opencv_speckles``), then the same
    depth and packed cloud. This branch's: ``compute_disparity`` (census byte planes, the
    padded packed-minimum kernel, the 3x3 sorting-network median, the union-find speckle
    filter). Both include decoding, depth and the message; the clouds are
    checked byte-equal on every frame.
    """
    import numba

    from stereo_depth import matching_cost as mc, pipeline as pl
    from stereo_depth.stereo_depth_node import prepare_pair, stereo_geometry
    from stereo_manip_tools.conversions import float32_fields_to_pointcloud2

    numba.set_num_threads(1)
    dmin, nd = int(params['min_disparity']), int(params['max_disparity'])
    dec = int(params['point_decimation'])
    p = pl.method_defaults('block_matching')
    cw, win = tuple(p['census_window']), tuple(p['window'])
    nbits = np.uint8(cw[0] * cw[1] - 1)

    import cv2

    from stereo_depth import refinement as rf

    main_kernel, main_nan_median = _main_kernel()

    def main_path(lm, rm):
        limg, rimg, colours = prepare_pair(lm, rm)
        h, w = limg.shape
        geo = stereo_geometry(infos[0], infos[1], w, h)
        lc = np.ascontiguousarray(limg[:, dmin:])
        rc = np.ascontiguousarray(rimg[:, :w - dmin])
        cl = mc.census_transform(lc, cw).astype(np.uint32)      # main's census_codes
        cr = mc.census_transform(rc, cw).astype(np.uint32)
        dl, dr = main_kernel(cl, cr, nd, win[0] // 2, win[1] // 2, nbits, 1, 0.0)
        d = rf.left_right_check(dl, dr, p['lr_max_diff'])
        d = opencv_speckles(d, p['speckle_size'], p['speckle_diff'])
        full = cv2.medianBlur(np.where(np.isfinite(d), d, np.float32(0.0)), p['median'])
        d = main_nan_median(d, p['median'] // 2, full, True)
        d = rf.fill_invalid(d, 'row')
        d[(d < 0.5) | (d > nd - 1.5)] = np.nan
        disp = np.full((h, w), np.nan, np.float32)
        disp[:, dmin:] = d + np.float32(dmin)
        depth = pl.disparity_to_depth(disp, geo['fx'], geo['baseline'], geo['doffs'])
        packed = pl.cloud_message_data(depth, geo['fx'], geo['fy'], geo['cx'], geo['cy'], dec,
                                       False, colours)
        return float32_fields_to_pointcloud2(packed.buffer, packed.fields, lm.header,
                                             is_dense=packed.is_dense)

    def branch_path(lm, rm):
        limg, rimg, colours = prepare_pair(lm, rm)
        h, w = limg.shape
        geo = stereo_geometry(infos[0], infos[1], w, h)
        disp = pl.compute_disparity(limg, rimg, 'block_matching', nd, min_disparity=dmin)
        depth = pl.disparity_to_depth(disp, geo['fx'], geo['baseline'], geo['doffs'])
        packed = pl.cloud_message_data(depth, geo['fx'], geo['fy'], geo['cx'], geo['cy'], dec,
                                       False, colours)
        return float32_fields_to_pointcloud2(packed.buffer, packed.fields, lm.header,
                                             is_dense=packed.is_dense)

    main_path(*frames[0])
    branch_path(*frames[0])
    t = {'main': [], 'branch': []}
    same = True
    for r in range(rounds):
        for i, (lm, rm) in enumerate(frames):
            out = {}
            order = (('main', main_path), ('branch', branch_path))
            for name, f in (order if (i + r) % 2 == 0 else order[::-1]):
                c0 = time.process_time()
                out[name] = f(lm, rm)
                t[name].append(1e3 * (time.process_time() - c0))
            same &= bytes(out['main'].data) == bytes(out['branch'].data)
    diff = [a - b for a, b in zip(t['main'], t['branch'])]
    return {'cpu_ms_per_frame': {'main': stats(t['main']), 'branch': stats(t['branch']),
                                 'main_minus_branch': stats(diff)},
            'clouds_identical': bool(same), 'frames': len(frames), 'rounds': rounds}


def node_before_after(frames, infos, params: Dict[str, Any], baseline_tree: str,
                      rounds: int) -> Dict[str, Any]:
    """
    Run the node process of ``baseline_tree`` (before) and of this tree (after) alternately.

    Part 4: ``rounds`` runs of each, in the order before/after, after/before, ... so that both
    see the same load; the before node is this tree's executable with the baseline tree's
    ``stereo_depth`` and ``stereo_manip_tools`` (its ``build/<package>`` directories) first on
    the ``PYTHONPATH``. Per-frame CPU of all runs pooled, and the median of each run.
    """
    base = Path(baseline_tree)
    path = os.pathsep.join(str(base / 'build' / package)
                           for package in ('stereo_depth', 'stereo_manip_tools'))
    for p in path.split(os.pathsep):
        if not (Path(p) / Path(p).name / '__init__.py').is_file():
            raise FileNotFoundError(f'{p} holds no built package; build {baseline_tree} first')
    values: Dict[str, List[float]] = {'before': [], 'after': []}
    runs: List[Dict[str, Any]] = []
    for r in range(rounds):
        for name in (('before', 'after') if r % 2 == 0 else ('after', 'before')):
            load0 = os.getloadavg()[0]
            out = node_process(frames, infos, params,
                               python_path=path if name == 'before' else '')
            values[name] += out['cpu_ms_per_frame_values']
            runs.append({'tree': name, 'cpu_ms_per_frame': out['cpu_ms_per_frame'],
                         'clouds_lost': out['clouds_lost'],
                         'minor_page_faults_per_frame_mean':
                             out['minor_page_faults_per_frame_mean'],
                         'load_1min': [load0, os.getloadavg()[0]]})
    per_run = {k: [run['cpu_ms_per_frame']['median'] for run in runs if run['tree'] == k]
               for k in values}
    return {'baseline_tree': str(base), 'rounds': rounds, 'runs': runs,
            'cpu_ms_per_frame_pooled': {k: stats(v) for k, v in values.items()},
            'run_medians': per_run,
            'median_of_run_medians': {k: float(np.median(v)) for k, v in per_run.items()}}


def main() -> None:
    """Run the three parts and write the report."""
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--frames', type=int, default=60, help='pairs measured')
    ap.add_argument('--note', default='', help='recorded in the JSON')
    ap.add_argument('--baseline-tree', default='',
                    help='part 4: a built checkout (e.g. /work/main) whose node runs '
                         'alternately with this one')
    ap.add_argument('--rounds', type=int, default=2, help='part 4: runs of each node')
    args = ap.parse_args()
    params = node_parameters()
    frames, infos = render_frames(args.frames)
    load_start = list(os.getloadavg())
    node = node_process(frames, infos, params)
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        profiled = node_process(frames, infos, params, profile_out=str(Path(tmp) / 'p.json'))
    split = stage_split(frames, infos, params)
    paired = paired_main_vs_branch(frames, infos, params)
    before_after = (node_before_after(frames, infos, params, args.baseline_tree, args.rounds)
                    if args.baseline_tree else None)
    load_end = list(os.getloadavg())
    for result in (node, profiled):
        result.pop('cpu_ms_per_frame_values', None)
    for k, v in split['cpu_ms'].items():
        print(f"{k:52s} {v['median']:7.2f} {v['p95']:7.2f} {v['max']:7.2f} ms CPU")
    c = node['cpu_ms_per_frame']
    for k, v in paired['cpu_ms_per_frame'].items():
        print(f"paired, {k:30s} {v['median']:7.2f} {v['p95']:7.2f} {v['max']:7.2f} ms CPU")
    for k, v in profiled.get('stages', {}).items():
        print(f"in node, {k:44s} process {v['process_cpu_ms']['median']:7.2f} thread "
              f"{v['thread_cpu_ms']['median']:7.2f} ms CPU (median per call, {v['calls']} calls)")
    print('node threads [ms CPU per frame]:', {k: round(v, 2) for k, v in
                                               node['cpu_ms_per_frame_by_thread'].items()})
    print(f"node process: {c['median']:.1f} / {c['p95']:.1f} / {c['max']:.1f} ms CPU per frame "
          f"(median / p95 / max), {node['clouds_lost']} clouds lost; load {load_end}")
    if before_after:
        for k, v in before_after['cpu_ms_per_frame_pooled'].items():
            print(f"node process {k:6s} {v['median']:7.2f} {v['p95']:7.2f} {v['max']:7.2f} ms "
                  f"CPU per frame (pooled), run medians {before_after['run_medians'][k]}")
        for run in before_after['runs']:
            print(f"  {run['tree']:6s} {run['cpu_ms_per_frame']['median']:7.2f} ms, "
                  f"{run['minor_page_faults_per_frame_mean']:.0f} page faults per frame, "
                  f"load {run['load_1min']}")
    packed = split['cpu_ms']['cloud build + pack (packed, this branch)']
    goals = [
        goal('stereo_depth_node process CPU per frame median [ms] (live peg_in_hole config)',
             50.0, '<=', c['median']),
        goal('cloud build + pack CPU per frame p95 [ms]', 10.0, '<=', packed['p95']),
        goal('clouds lost in lock-step', 0, '==', node['clouds_lost']),
        goal('per-frame CPU main - branch, median of paired frames [ms] (> 0: cheaper)', 0.0,
             '>', paired['cpu_ms_per_frame']['main_minus_branch']['median']),
        goal('clouds of main and branch identical on every paired frame', 1, '==',
             int(paired['clouds_identical'])),
    ]
    write_report('stereo_node_cpu', goals, scene=SCENE, image_size=[640, 480],
                 node_process=node, in_process_stage_split=split,
                 node_process_profiled={k: profiled.get(k) for k in (
                     'stages', 'cpu_ms_per_frame', 'cpu_ms_per_frame_by_thread', 'clouds_lost')},
                 paired_main_vs_branch=paired, node_process_before_after=before_after,
                 load_average={'start': load_start, 'end': load_end}, note=args.note)


if __name__ == '__main__':
    main()
