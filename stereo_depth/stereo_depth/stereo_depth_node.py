"""
``stereo_depth_node``: rectified stereo pairs -> disparity, depth and a point cloud.

Subscribes (sensor-data QoS; topic names as ``stereo_image_proc``):
``left/image_rect``, ``right/image_rect`` (mono8, 8UC1, mono16, 16UC1, rgb8, bgr8, rgba8, bgra8),
``left/camera_info``, ``right/camera_info``.

Publishes:
``disparity`` (``stereo_msgs/DisparityImage``, 32FC1 pixels ``d = x_l - x_r - (cx_l - cx_r)``,
missing pixels ``min_disparity - 1``, i.e. -1 for the usual rectification), ``depth``
(``sensor_msgs/Image`` 32FC1, metres along the optical axis, NaN where unknown), ``points2``
(``sensor_msgs/PointCloud2`` x, y, z [m] and rgb for colour input, in the left optical frame of
the image header).

Only outputs with a subscriber are built (none at all: the pair is not even matched, and
counted as ``skipped_unsubscribed``). Publishers and subscriptions keep one message (depth 1):
a slow reader loses old samples instead of queueing them.

Point cloud: every ``point_decimation``-th pixel in both directions; ``organized_cloud`` publishes
the H/s x W/s grid with NaN points where the depth is unknown (``is_dense`` false), otherwise
only the valid points (height 1). The search range is ``min_disparity`` .. ``min_disparity +
max_disparity - 1`` px. The ``stereo_image_proc`` parameter names ``disparity_range``,
``correlation_window_size``, ``speckle_range``, ``uniqueness_ratio``, ``P1``, ``P2``,
``disp12_max_diff``, ``stereo_algorithm`` (0 = opencv_bm, 1 = opencv_sgbm) and ``queue_size``
are accepted as aliases of the node's own parameters (set at start or at run time).

Threads: numba's parallel kernels run on the ``numba_threading_layer`` (default ``workqueue``:
OpenMP's spinning threads cost ~20 ms CPU per frame that the other nodes of the graph need)
with ``numba_threads`` threads. Memory: ``main`` keeps freed memory in the process
(:func:`stereo_manip_tools.memory.retain_freed_memory`), so each frame's arrays reuse the pages of
the previous frame instead of faulting in new ones.

Pairing: left and right images are paired by header stamp, exactly by default or within
``sync_tolerance`` seconds; each pair uses the camera infos with the same stamp, else the latest
received ones. Processing runs in a worker thread on the newest pair only: a pair that is
superseded before the worker takes it is dropped and counted (``dropped_stale``), never
queued. With ``max_rate`` the pairs beyond that rate (by their stamps: every third of a 30 Hz
camera at 10 Hz) are skipped at the input and counted (``skipped_rate``). Bad input (size
mismatch, unsupported encoding, missing or inconsistent camera info, zero baseline) is rejected
with a warning naming the problem and counted per reason. The processing rate and the counters
are logged every ``stats_period`` seconds.
"""

from __future__ import annotations

from collections import OrderedDict
import copy
import threading
import time
from typing import Any, Dict, Optional, Tuple

import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, RegionOfInterest
from stereo_depth.pipeline import (available_methods, cloud_message_data, compute_disparity,
                                   disparity_to_depth, method_defaults)
from stereo_manip_tools.conversions import (CameraInfoError, float32_fields_to_pointcloud2,
                                            image_to_numpy, numpy_to_image, stamp_to_ns,
                                            stereo_parameters_from_camera_info)
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.memory import retain_freed_memory
from stereo_manip_tools.parameters import bool_descriptor, float_descriptor, \
    INPUT_QOS_CHOICES, input_qos_descriptor, input_qos_profile, int_descriptor, \
    reject_nonfinite_parameters, string_descriptor
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections, \
    spin_until_shutdown
from stereo_manip_tools.sync import StampRateLimiter, StampSynchronizer
from stereo_manip_tools.tf import publish_camera_mount
from stereo_manip_tools.worker import NewestOnlyWorker
from stereo_msgs.msg import DisparityImage

__all__ = ['StereoDepthNode', 'prepare_pair', 'stereo_geometry', 'main', 'SUPPORTED_ENCODINGS',
           'ALIASES', 'alias_value', 'select_numba_threads', 'NUMBA_THREADING_LAYERS']

SUPPORTED_ENCODINGS = ('mono8', '8UC1', 'mono16', '16UC1', 'rgb8', 'bgr8', 'rgba8', 'bgra8')

# Parameters forwarded to the method when it has a parameter of that name.
_METHOD_PARAMS = ('p1', 'p2', 'block_size', 'lr_check', 'lr_max_diff', 'speckle_size',
                  'speckle_diff', 'median', 'fill', 'uniqueness')


class InputError(ValueError):
    """A frame that cannot be processed; ``reason`` is the counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def _to_matching_image(img: np.ndarray, encoding: str) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """(image for matching: uint8 grey or RGB, RGB uint8 colours for the cloud or None)."""
    if encoding in ('mono16', '16UC1'):
        img = (img >> 8).astype(np.uint8)
    if encoding in ('mono8', '8UC1', 'mono16', '16UC1'):
        return img, None
    rgb = img[:, :, :3]
    if encoding in ('bgr8', 'bgra8'):
        rgb = rgb[:, :, ::-1]
    rgb = np.ascontiguousarray(rgb)
    return rgb, rgb


def prepare_pair(left: Image, right: Image) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """
    Decode and check a left/right image pair.

    :return: (left, right) arrays for matching and the left RGB colours (None for mono).
    :raises InputError: unsupported/mismatched encodings, or images of different sizes.
    """
    for side, msg in (('left', left), ('right', right)):
        if msg.encoding not in SUPPORTED_ENCODINGS:
            raise InputError('unsupported_encoding',
                             f'{side} image has unsupported encoding {msg.encoding!r}; '
                             f'supported: {", ".join(SUPPORTED_ENCODINGS)}')
    if left.encoding != right.encoding:
        raise InputError('encoding_mismatch', f'left image is {left.encoding} but right image '
                                              f'is {right.encoding}')
    if (left.width, left.height) != (right.width, right.height):
        raise InputError('size_mismatch', f'left image is {left.width}x{left.height} but right '
                                          f'image is {right.width}x{right.height}')
    if left.width == 0 or left.height == 0:
        raise InputError('size_mismatch', 'empty image (width or height 0)')
    try:
        limg = image_to_numpy(left)
        rimg = image_to_numpy(right)
    except ValueError as exc:
        raise InputError('bad_image', f'cannot decode image: {exc}') from exc
    lm, colours = _to_matching_image(limg, left.encoding)
    rm, _ = _to_matching_image(rimg, right.encoding)
    return lm, rm, colours


def stereo_geometry(left_info: Optional[CameraInfo], right_info: Optional[CameraInfo],
                    width: int, height: int) -> Dict[str, float]:
    """
    fx, fy, cx, cy, baseline [m] and doffs = cx_r - cx_l [px] from the rectified infos.

    The infos are parsed by
    :func:`stereo_manip_tools.conversions.stereo_parameters_from_camera_info` (ROS convention:
    right ``P[0, 3] = -fx * B``; depth ``Z = fx B / (d + doffs)``); this adds the checks
    against the frame: both infos received and of the images' size.

    :raises InputError: missing info, zero focal length, baseline not positive, or an info
        whose size differs from the images (``reason`` is the counter key).
    """
    if left_info is None or right_info is None:
        missing = [n for n, i in (('left/camera_info', left_info),
                                  ('right/camera_info', right_info)) if i is None]
        raise InputError('missing_camera_info',
                         f'no CameraInfo received on {" and ".join(missing)}')
    for side, info in (('left', left_info), ('right', right_info)):
        if (info.width, info.height) != (width, height):
            raise InputError('size_mismatch',
                             f'{side} CameraInfo is {info.width}x{info.height} but the images '
                             f'are {width}x{height}')
    try:
        params = stereo_parameters_from_camera_info(left_info, right_info)
    except CameraInfoError as exc:
        raise InputError(exc.reason, str(exc)) from exc
    return {'fx': params.fx, 'fy': params.fy, 'cx': params.cx, 'cy': params.cy,
            'baseline': params.baseline, 'doffs': params.doffs}


_PARAMS = {
    # name: (default, descriptor)
    'method': ('block_matching', string_descriptor(
        'disparity method (stereo_depth.pipeline): ' + ', '.join(available_methods()),
        additional_constraints='one of ' + ', '.join(available_methods()))),
    'max_disparity': (64, int_descriptor(
        'number of disparity candidates D (min_disparity .. min_disparity + D - 1 pixels)',
        2, 512)),
    'min_disparity': (0, int_descriptor(
        "smallest disparity searched [px]; set it to the scene's nearest-far bound to search "
        'only the band the scene occupies', 0, 1024)),
    'point_decimation': (1, int_descriptor(
        'points2 keeps every n-th pixel in both directions (1 = all; 2 = a quarter of the '
        'points)', 1, 16)),
    'organized_cloud': (False, bool_descriptor(
        'points2 as the organised H/n x W/n grid with NaN where the depth is unknown '
        '(default: only the valid points, height 1)')),
    'numba_threading_layer': ('workqueue', string_descriptor(
        'numba threading layer of the parallel kernels: workqueue (no spinning threads), omp, '
        "tbb or default (numba's choice)", read_only=True,
        additional_constraints='one of workqueue, omp, tbb, default')),
    'numba_threads': (0, int_descriptor(
        'threads of the parallel kernels (0 = one per core)', 0, 256, read_only=True)),
    'sync_tolerance': (0.0, float_descriptor(
        'largest stamp difference [s] between paired left/right images; 0 = exact stamps',
        0.0, 1.0)),
    'input_qos': ('sensor_data', input_qos_descriptor('image and camera_info')),
    'sync_queue_size': (10, int_descriptor(
        'images kept per side while waiting for the partner', 1, 100, read_only=True)),
    'publish_points': (True, bool_descriptor('publish the point cloud on points2')),
    'max_rate': (0.0, float_descriptor(
        "largest rate [Hz, of the pairs' stamps] of pairs processed; the others are skipped "
        'at the input and counted (a camera faster than the graph can follow degrades by '
        'dropping, with bounded latency); 0 = every pair', 0.0, 1000.0)),
    'stats_period': (5.0, float_descriptor(
        'period [s] of the processing-rate log line', 0.5, 3600.0, read_only=True)),
    'p1': (10, int_descriptor('SGM penalty of a 1-pixel disparity change (sgm, sgm4)',
                              0, 1000)),
    'p2': (90, int_descriptor('SGM penalty of larger disparity changes, >= p1 (sgm, sgm4)',
                              0, 4000)),
    'block_size': (5, int_descriptor('OpenCV block size (opencv_bm needs odd >= 5, '
                                     'opencv_sgbm odd >= 1)', 1, 51)),
    'lr_check': (True, bool_descriptor('left-right consistency check (own methods)')),
    'lr_max_diff': (1.0, float_descriptor('left-right check tolerance [px]', 0.0, 10.0)),
    'speckle_size': (100, int_descriptor('largest blob [px] removed as a speckle; 0 = off',
                                         0, 10000)),
    'speckle_diff': (1.0, float_descriptor('disparity step [px] separating speckle blobs',
                                           0.0, 16.0)),
    'median': (3, int_descriptor('median filter window (odd; 1 = off)', 1, 7)),
    'fill': (True, bool_descriptor('fill missing pixels from the background (dense output)')),
    'uniqueness': (0.0, float_descriptor('SGM uniqueness margin (0 = off)', 0.0, 1.0)),
}


NUMBA_THREADING_LAYERS = ('workqueue', 'omp', 'tbb', 'default')

# stereo_image_proc (disparity_node) name -> (own parameter, conversion, description)
ALIASES = {
    'disparity_range': ('max_disparity', int, 'stereo_image_proc name of max_disparity'),
    'correlation_window_size': ('block_size', int, 'stereo_image_proc name of block_size'),
    'speckle_range': ('speckle_diff', float, 'stereo_image_proc name of speckle_diff [px]'),
    'uniqueness_ratio': ('uniqueness', lambda v: float(v) / 100.0,
                         'stereo_image_proc uniqueness ratio [%] = 100 x uniqueness'),
    'P1': ('p1', lambda v: int(round(v)), 'stereo_image_proc name of p1'),
    'P2': ('p2', lambda v: int(round(v)), 'stereo_image_proc name of p2'),
    'disp12_max_diff': ('lr_max_diff', float, 'stereo_image_proc name of lr_max_diff [px]'),
    'stereo_algorithm': ('method', lambda v: {0: 'opencv_bm', 1: 'opencv_sgbm'}[int(v)],
                         'stereo_image_proc algorithm: 0 = opencv_bm, 1 = opencv_sgbm'),
    'queue_size': ('sync_queue_size', int, 'stereo_image_proc name of sync_queue_size'),
}


def alias_value(alias: str, value: Any) -> Tuple[str, Any]:
    """
    (own parameter name, converted value) of a ``stereo_image_proc`` alias.

    :raises ValueError: the value cannot be converted (e.g. stereo_algorithm 2).
    """
    target, convert, _ = ALIASES[alias]
    if isinstance(value, (bool, str)) and target != 'method':
        raise ValueError(f'{alias} must be a number, got {value!r}')
    try:
        return target, convert(value)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f'{alias}={value!r} cannot be used as {target}: {exc}') from exc


def select_numba_threads(layer: str, threads: int) -> str:
    """
    Choose numba's threading layer and thread count before the first parallel kernel.

    :param layer: one of :data:`NUMBA_THREADING_LAYERS` ('default' keeps numba's choice).
    :param threads: threads of the parallel kernels (0 = numba's default, one per core).
    :return: the layer in use after the threads were started.
    """
    import numba
    if layer not in NUMBA_THREADING_LAYERS:
        raise ValueError(f'numba_threading_layer must be one of {NUMBA_THREADING_LAYERS}, '
                         f'got {layer!r}')
    if layer != 'default':
        numba.config.THREADING_LAYER = layer
    if threads > 0:
        numba.set_num_threads(min(int(threads), numba.config.NUMBA_NUM_THREADS))
    else:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)   # starts the layer
    return numba.threading_layer()


def _range_violation(name: str, value: Any) -> Optional[str]:
    """Reason ``value`` is outside the declared range of parameter ``name``, or None."""
    desc = _PARAMS[name][1]
    for r in list(desc.integer_range) + list(desc.floating_point_range):
        if not r.from_value <= value <= r.to_value:
            return f'{name}={value} is outside [{r.from_value}, {r.to_value}]'
    return None


def validate_parameter(name: str, value: Any, current: Dict[str, Any]) -> Optional[str]:
    """Reason the new value is invalid, or None (cross-parameter rules included)."""
    if name == 'method' and value not in available_methods():
        return f"method must be one of {available_methods()}, got '{value}'"
    if name == 'numba_threading_layer' and value not in NUMBA_THREADING_LAYERS:
        return f'numba_threading_layer must be one of {NUMBA_THREADING_LAYERS}, got {value!r}'
    if name == 'input_qos' and value not in INPUT_QOS_CHOICES:
        return f"input_qos must be one of {INPUT_QOS_CHOICES}, got '{value}'"
    if name == 'median' and value % 2 == 0:
        return f'median window must be odd, got {value}'
    if name == 'block_size' and value % 2 == 0:
        return f'block_size must be odd, got {value}'
    if name == 'p1' and value > current.get('p2', value):
        return f'p1={value} must not exceed p2={current.get("p2")}'
    if name == 'p2' and value < current.get('p1', value):
        return f'p2={value} must not be below p1={current.get("p1")}'
    return None


class StereoDepthNode(Node):
    """Stereo pairs in, disparity/depth/points out (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('stereo_depth_node', **kwargs)
        self._params: Dict[str, Any] = {}
        self._lock = threading.Lock()
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        for name, (default, desc) in _PARAMS.items():
            self._params[name] = self.declare_parameter(name, default, desc).value
        for alias, (target, _, text) in ALIASES.items():
            # Untyped and unset unless given; the callback applies it to its own parameter.
            value = self.declare_parameter(alias, None, ParameterDescriptor(
                description=f'{text} (alias; sets {target})', dynamic_typing=True,
                read_only=_PARAMS[target][1].read_only)).value
            if value is not None:
                self._params[target] = alias_value(alias, value)[1]
        self.numba_layer = select_numba_threads(self._params['numba_threading_layer'],
                                                int(self._params['numba_threads']))

        self._sync = StampSynchronizer(
            ('left', 'right'), tolerance_ns=int(round(self._params['sync_tolerance'] * 1e9)),
            queue_size=int(self._params['sync_queue_size']))
        self._rate_limit = StampRateLimiter(float(self._params['max_rate']))
        self._infos: Dict[str, 'OrderedDict[int, CameraInfo]'] = {'left': OrderedDict(),
                                                                  'right': OrderedDict()}
        self.counters: Dict[str, int] = {'received_pairs': 0, 'processed': 0,
                                         'dropped_stale': 0, 'unpaired_images': 0, 'failed': 0,
                                         'skipped_unsubscribed': 0, 'skipped_rate': 0}
        self.rejected: Dict[str, int] = {}
        self._last_warning: Dict[str, float] = {}
        self._proc_times: list = []

        self.pub_disparity = self.create_publisher(DisparityImage, 'disparity', 1)
        self.pub_depth = self.create_publisher(Image, 'depth', 1)
        self.pub_points = self.create_publisher(PointCloud2, 'points2', 1)
        qos = copy.copy(input_qos_profile(self._params['input_qos'], depth=1))
        qos.depth = 1       # drop, do not queue: the newest pair is the one worth matching
        guard = InputRejections(self.get_logger()).guard   # last line of defence
        for side in ('left', 'right'):
            self.create_subscription(Image, f'{side}/image_rect', guard(
                lambda m, s=side: self._on_image(s, m), f'{side}/image_rect'), qos)
            self.create_subscription(CameraInfo, f'{side}/camera_info', guard(
                lambda m, s=side: self._on_info(s, m), f'{side}/camera_info'), qos)
        self._stats_t0 = time.monotonic()
        self._stats_processed = 0
        self.create_timer(float(self._params['stats_period']), self._log_stats)
        self.camera_mount = publish_camera_mount(self)   # static TF parent -> optical frame
        self.diagnostics = NodeDiagnostics(self, lambda: {**self.counters, **{  # /diagnostics
            f'rejected_{k}': v for k, v in dict(self.rejected).items()}})
        self._worker = NewestOnlyWorker(
            self._work, 'stereo_depth_worker', self._lock, prepare=self._warm_up,
            take=lambda pair: (pair, dict(self._params),
                               self._infos_for(stamp_to_ns(pair['left'].header.stamp))))
        self._worker.start()
        self.get_logger().info(
            f"stereo_depth_node ready: method {self._params['method']}, "
            f"{self._params['max_disparity']} disparities from {self._params['min_disparity']}, "
            f"points every {self._params['point_decimation']} px"
            + (' (organised)' if self._params['organized_cloud'] else '')
            + f', numba {self.numba_layer} layer, sync '
            + ('exact' if self._params['sync_tolerance'] == 0
               else f"within {self._params['sync_tolerance']} s"))

    # --- parameters --------------------------------------------------------------------------

    def _on_set_parameters(self, params) -> SetParametersResult:
        current = dict(self._params)
        updates: Dict[str, Any] = {}
        for p in params:
            name, value = p.name, p.value
            if name in ALIASES:
                if p.type_ == Parameter.Type.NOT_SET or value is None:
                    continue
                try:
                    name, value = alias_value(p.name, value)
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
                reason = _range_violation(name, value)     # rclpy checks only declared names
                if reason is not None:
                    return SetParametersResult(successful=False,
                                               reason=f'{p.name} (alias): {reason}')
            if name in _PARAMS:
                reason = validate_parameter(name, value, current)
                if reason is not None:
                    return SetParametersResult(successful=False, reason=reason)
                current[name] = value
                updates[name] = value
        with self._lock:
            self._params.update(updates)
            if 'sync_tolerance' in updates and hasattr(self, '_sync'):
                self._sync.tolerance_ns = int(round(updates['sync_tolerance'] * 1e9))
            if 'max_rate' in updates and hasattr(self, '_rate_limit'):
                self._rate_limit.max_rate = float(updates['max_rate'])
        return SetParametersResult(successful=True)

    # --- input ---------------------------------------------------------------------------------

    def _reject(self, reason: str, message: str) -> None:
        # Every rejection is counted; the warning is repeated at most once per second and
        # reason, so a misconfigured 30 Hz camera does not flood the log.
        now = time.monotonic()
        with self._lock:
            self.rejected[reason] = self.rejected.get(reason, 0) + 1
            n = self.rejected[reason]
            last = self._last_warning.get(reason)
            if last is not None and now - last < 1.0:
                return
            self._last_warning[reason] = now
        self.get_logger().warning(f'frame rejected ({reason}, {n} so far): {message}')

    def _on_info(self, side: str, msg: CameraInfo) -> None:
        with self._lock:
            q = self._infos[side]
            q[stamp_to_ns(msg.header.stamp)] = msg
            while len(q) > 50:
                q.popitem(last=False)

    def _on_image(self, side: str, msg: Image) -> None:
        with self._lock:
            before = sum(self._sync.dropped.values())
            pair = self._sync.add(side, stamp_to_ns(msg.header.stamp), msg)
            unpaired = sum(self._sync.dropped.values()) - before
            if unpaired:
                self.counters['unpaired_images'] += unpaired
            if pair is None:
                return
            self.counters['received_pairs'] += 1
            if not self._rate_limit.admit(stamp_to_ns(msg.header.stamp)):
                self.counters['skipped_rate'] += 1          # beyond max_rate
                return
            if self._worker.put(pair):
                self.counters['dropped_stale'] += 1       # superseded before processing

    def _infos_for(self, stamp_ns: int) -> Tuple[Optional[CameraInfo], Optional[CameraInfo]]:
        tol = int(round(self._params['sync_tolerance'] * 1e9))
        out = []
        for side in ('left', 'right'):
            q = self._infos[side]
            if not q:
                out.append(None)
                continue
            best = min(q, key=lambda s: abs(s - stamp_ns))
            out.append(q[best] if abs(best - stamp_ns) <= tol else q[next(reversed(q))])
        return out[0], out[1]

    # --- processing ----------------------------------------------------------------------------

    def _warm_up(self) -> None:
        """
        Load numba's compiled kernels by matching one small random pair.

        Match one small random pair with the configured method, so numba's compiled kernels
        are loaded before the first real pair (otherwise that pair is late by seconds).
        """
        t0 = time.perf_counter()
        params = dict(self._params)
        ndisp, dmin = int(params['max_disparity']), int(params['min_disparity'])
        rng = np.random.default_rng(0)
        w = ndisp + dmin + 32
        left = rng.integers(0, 256, (32, w), dtype=np.uint8)
        right = np.ascontiguousarray(np.roll(left, -(dmin + 1), axis=1))
        defaults = method_defaults(params['method'])
        mp = {k: params[k] for k in _METHOD_PARAMS if k in defaults}
        if params['method'].startswith('opencv'):
            mp.pop('p1', None)
            mp.pop('p2', None)
        try:
            disp = compute_disparity(left, right, params['method'], ndisp, min_disparity=dmin,
                                     **mp)
            cloud_message_data(disparity_to_depth(disp, 100.0, 0.1), 100.0, 100.0, w / 2, 16.0,
                               int(params['point_decimation']), bool(params['organized_cloud']))
        except ValueError as exc:       # e.g. a band the warm-up image cannot hold
            self.get_logger().warning(f'warm-up skipped: {exc}')
            return
        self.get_logger().info(f'warm-up (kernels loaded) in {time.perf_counter() - t0:.2f} s')

    def _work(self, taken: Tuple[Dict[str, Image], Dict[str, Any], Any]) -> None:
        """Process a pair with the parameters and camera infos taken along with it."""
        pair, params, infos = taken
        try:
            self._process(pair['left'], pair['right'], infos, params)
        except InputError as exc:
            self._reject(exc.reason, str(exc))
        except ValueError as exc:
            self._reject('invalid', str(exc))
        except Exception as exc:  # noqa: BLE001 - keep the node alive, count and report
            with self._lock:
                self.counters['failed'] += 1
            self.get_logger().error(f'processing failed: {type(exc).__name__}: {exc}')

    def _process(self, left: Image, right: Image, infos, params: Dict[str, Any]) -> None:
        want_disparity = self.pub_disparity.get_subscription_count() > 0
        want_depth = self.pub_depth.get_subscription_count() > 0
        want_points = params['publish_points'] and self.pub_points.get_subscription_count() > 0
        if not (want_disparity or want_depth or want_points):
            with self._lock:
                self.counters['skipped_unsubscribed'] += 1
            return
        t0 = time.perf_counter()
        limg, rimg, colours = prepare_pair(left, right)
        h, w = limg.shape[:2]
        geo = stereo_geometry(infos[0], infos[1], w, h)
        method = params['method']
        ndisp, dmin = int(params['max_disparity']), int(params['min_disparity'])
        if ndisp + dmin > w:
            raise InputError('invalid', f'min_disparity {dmin} + max_disparity {ndisp} exceeds '
                                        f'the image width {w}')
        defaults = method_defaults(method)
        mp = {k: params[k] for k in _METHOD_PARAMS if k in defaults}
        if method.startswith('opencv'):
            # OpenCV SGBM keeps its own P1 = 8 bs^2, P2 = 32 bs^2 (node p1/p2 are for SGM)
            mp.pop('p1', None)
            mp.pop('p2', None)
        disp = compute_disparity(limg, rimg, method, ndisp, min_disparity=dmin, **mp)
        header = left.header
        with self._lock:
            # counted before publishing, so a subscriber never sees more outputs than counts
            self.counters['processed'] += 1
            self._proc_times.append(time.perf_counter() - t0)
        if want_disparity:
            self.pub_disparity.publish(self._disparity_message(disp, geo, header, dmin, ndisp))
        depth = None
        if want_depth:
            depth = disparity_to_depth(disp, geo['fx'], geo['baseline'], geo['doffs'])
            self.pub_depth.publish(numpy_to_image(depth, '32FC1', header))
        if want_points:
            # the depth image when it was built, else the depth of the kept pixels only, bit
            # for bit disparity_to_depth's (tested)
            camera = (geo['fx'], geo['fy'], geo['cx'], geo['cy'],
                      int(params['point_decimation']), bool(params['organized_cloud']), colours)
            if depth is not None:
                packed = cloud_message_data(depth, *camera)
            else:
                packed = cloud_message_data(None, *camera, disparity=disp,
                                            baseline=geo['baseline'], doffs=geo['doffs'])
            msg = float32_fields_to_pointcloud2(packed.buffer, packed.fields, header,
                                                is_dense=packed.is_dense)
            self.pub_points.publish(msg)

    @staticmethod
    def _disparity_message(disp: np.ndarray, geo: Dict[str, float], header, dmin: int,
                           ndisp: int) -> DisparityImage:
        h, w = disp.shape
        # Disparity relative to the principal points, as DisparityImage defines it; one
        # float32 image written in place (NaN -> below min_disparity), no float64 temporaries.
        out = np.add(disp, np.float32(geo['doffs']), dtype=np.float32)
        np.copyto(out, np.float32(geo['doffs'] + dmin - 1.0), where=~np.isfinite(out))
        dmsg = DisparityImage()
        dmsg.header = header
        dmsg.image = numpy_to_image(out, '32FC1', header)
        dmsg.f = geo['fx']
        dmsg.t = geo['baseline']
        dmsg.valid_window = RegionOfInterest(x_offset=dmin, y_offset=0, height=h,
                                             width=w - dmin)
        dmsg.min_disparity = float(dmin + geo['doffs'])
        dmsg.max_disparity = float(dmin + ndisp - 1 + geo['doffs'])
        dmsg.delta_d = 1.0 / 16.0
        return dmsg

    def _log_stats(self) -> None:
        now = time.monotonic()
        with self._lock:
            n = self.counters['processed'] - self._stats_processed
            self._stats_processed = self.counters['processed']
            times = self._proc_times
            self._proc_times = []
            counters = dict(self.counters)
            rejected = dict(self.rejected)
        period = now - self._stats_t0
        self._stats_t0 = now
        ms = 1e3 * float(np.mean(times)) if times else float('nan')
        self.get_logger().info(
            f'processed {n} frames in {period:.1f} s ({n / period:.2f} Hz, {ms:.1f} ms/frame); '
            f"total processed {counters['processed']}, pairs {counters['received_pairs']}, "
            f"dropped stale {counters['dropped_stale']}, unpaired images "
            f"{counters['unpaired_images']}, failed {counters['failed']}, skipped (no subscriber) "
            f"{counters['skipped_unsubscribed']}, skipped (max_rate) {counters['skipped_rate']}, "
            f'rejected {sum(rejected.values())} {rejected}')

    def destroy_node(self) -> None:
        self._worker.stop(timeout=5.0)
        super().destroy_node()


def main(args=None):
    # Every frame allocates the same ~1 MB arrays; glibc would unmap them when freed and the
    # next frame would fault in fresh pages (~2100 page faults and ~12 ms CPU per 640x480
    # frame in bench/stereo_node_cpu.py).
    retained = retain_freed_memory()
    rclpy.init(args=args)
    node = create_node_or_exit(StereoDepthNode, 'stereo_depth_node')
    if not retained:
        node.get_logger().warning('freed memory is returned to the kernel (no glibc mallopt): '
                                  'page faults add CPU to every frame')
    spin_until_shutdown(node)
