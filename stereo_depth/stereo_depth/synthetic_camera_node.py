"""
The ``synthetic_camera`` node: a stereo camera driver that renders built-in scenes.

``synthetic_camera``: a stereo camera driver that renders built-in scenes (or replays a
still real pair) and publishes it like real hardware, with exact ground truth.

Published topics (all with the same header stamp per frame: the time the pair was rendered,
i.e. its "exposure"; with ``trigger`` false the camera free-runs at ``rate``):

* ``left/image_rect``, ``right/image_rect`` (sensor_msgs/Image, mono8 or rgb8, rectified);
* ``left/camera_info``, ``right/camera_info`` (sensor_msgs/CameraInfo; right ``P[3] = -fx B``);
* ground truth unless ``ground_truth`` is false: ``objects/<name>/pose_truth``
  (geometry_msgs/PoseStamped, object pose in the left optical frame), ``depth_truth``
  (sensor_msgs/Image 32FC1, metres, NaN background, REP 118), ``disparity_truth``
  (stereo_msgs/DisparityImage; background marked -1, below ``min_disparity``),
  ``occlusion_truth`` (sensor_msgs/Image mono8, 255 where the left pixel is not seen by the
  right camera).

Free-running, the camera keeps its rate like hardware with its own clock: frames are due on a
steady grid of period ``1 / rate`` (:class:`FrameGrid`), and a wake-up that comes more than a
period late (a loaded machine, a publish blocked on a full network link) still renders the
missed frames, up to ``catch_up_frames`` of them; older ones are dropped and counted
(``dropped_frames`` and ``caught_up_frames`` in /diagnostics), never skipped silently.

The optical frames follow REP 103 (z forward, x right, y down); the left one is the reference.
Parameters are validated when declared and when set; a refused value keeps the old one and
the reason is returned to the caller and logged.
"""

from __future__ import annotations

import math
import sys
import time
from typing import Dict, List, Optional, Tuple

from geometry_msgs.msg import PoseStamped
import numpy as np
from rcl_interfaces.msg import (
    FloatingPointRange, IntegerRange, ParameterDescriptor, SetParametersResult)
import rclpy
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Empty, Header
from stereo_depth.synthetic import (
    load_motorcycle, load_stereo_files, RealStereoPair, RenderOptions, SCENES, StereoCamera,
    SyntheticStereo)
from stereo_manip_tools.conversions import (
    camera_info_from_parameters, matrix_to_pose_stamped, numpy_to_image,
    StereoCameraParameters)
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.robustness import spin_until_shutdown
from stereo_msgs.msg import DisparityImage

__all__ = ['SyntheticCameraNode', 'main', 'SOURCES', 'ENCODINGS', 'PLAYBACKS', 'scene_frame',
           'FrameGrid']

SOURCES = ('synthetic', 'motorcycle', 'files')
ENCODINGS = ('mono8', 'rgb8')
PLAYBACKS = ('loop', 'bounce')


def scene_frame(count: int, n_frames: int, playback: str) -> int:
    """
    Scene frame shown at the ``count``-th advanced frame index.

    ``loop`` returns ``count`` (the scene wraps it around itself); ``bounce`` runs 0, 1, ...,
    n-1, n-2, ..., 1, 0, 1, ... (a triangle wave with period 2 (n - 1)).
    """
    if playback == 'loop' or n_frames < 2:
        return int(count)
    period = 2 * (n_frames - 1)
    k = int(count) % period
    return k if k < n_frames else period - k


class FrameGrid:
    """
    Exposure times of a free-running camera: frame ``k`` is due at ``t0 + k / rate`` [s].

    The ROS timer only wakes the camera; which frames are due is decided here, on a steady
    clock. A wake-up that comes more than a period late (a loaded machine: the rcl timer then
    skips the missed periods) still yields every frame whose time has passed, up to
    ``1 + catch_up`` frames per wake-up, like the frames a camera driver keeps in its buffer
    ring; older ones are dropped and counted. So the camera keeps its rate on average
    whenever rendering keeps up on average, and says how many frames it lost when it does not.
    A wake-up ahead of the grid (the timer's phase drifted below the anchor) re-anchors the
    grid on it.

    Pure Python (no rclpy); ``now`` values come from one steady clock, e.g. ``time.monotonic``.
    """

    def __init__(self, rate: float, catch_up: int) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ValueError(f'rate must be > 0 Hz, got {rate}')
        if catch_up < 0:
            raise ValueError(f'catch_up must be >= 0 frames, got {catch_up}')
        self.rate = float(rate)
        self.catch_up = int(catch_up)
        self.t0: Optional[float] = None
        self.next_index = 0          # grid index of the next frame to render

    def reset(self) -> None:
        """Start a new grid at the next wake-up (after a rate change or a rebuild)."""
        self.t0 = None
        self.next_index = 0

    def due(self, now: float) -> Tuple[int, int]:
        """
        Frames to render now and frames dropped (older than the catch-up allows).

        :param now: the wake-up time [s] on the grid's steady clock.
        :returns: ``(render, dropped)``; ``render >= 1``: a wake-up always yields a frame.
        """
        if self.t0 is None:
            self.t0 = float(now)
            self.next_index = 0
        # 5 % of a period of slack: float noise never turns an on-time wake-up into a miss
        k_due = math.floor((now - self.t0) * self.rate + 0.05)
        n = k_due - self.next_index + 1
        if n <= 0:                   # woken before the grid's next frame: re-anchor on it
            self.t0 = float(now) - self.next_index / self.rate
            n = 1
        dropped = max(0, n - 1 - self.catch_up)
        render = n - dropped
        self.next_index += n
        return render, dropped


def _float_range(lo: float, hi: float) -> List[FloatingPointRange]:
    return [FloatingPointRange(from_value=lo, to_value=hi, step=0.0)]


def _int_range(lo: int, hi: int) -> List[IntegerRange]:
    return [IntegerRange(from_value=lo, to_value=hi, step=1)]


# name: (default, description, extra descriptor fields)
_PARAMS = {
    'source': ('synthetic', f'Image source: one of {", ".join(SOURCES)}.', {}),
    'scene': ('peg_in_hole', f'Built-in scene (source=synthetic): one of {", ".join(SCENES)}.',
              {}),
    'seed': (0, 'Seed of the scene parameters, texture and noise (deterministic output).',
             {'integer_range': _int_range(0, 2 ** 31 - 1)}),
    'rate': (30.0, 'Publishing rate [Hz] (> 0).',
             {'floating_point_range': _float_range(0.01, 1000.0)}),
    'start_frame': (0, 'Scene frame index of the first published frame.',
                    {'integer_range': _int_range(0, 2 ** 31 - 1)}),
    'catch_up_frames': (3, 'Free-running: frames still rendered (late) after the camera was '
                           'woken more than a period late, like the frames a camera driver '
                           'buffers; older missed frames are dropped and counted '
                           '(dropped_frames). 0 = skip every missed period.',
                        {'integer_range': _int_range(0, 100)}),
    'trigger': (False, 'Software trigger: publish one frame per std_msgs/Empty received on '
                       '`trigger` instead of at `rate` (read-only; set at start-up).',
                {'read_only': True}),
    'frame_step': (1, 'Scene frames advanced per published frame (1 = the scene at its own '
                      'fps when rate matches it; > 1 plays it faster, like a time lapse).',
                   {'integer_range': _int_range(1, 1000)}),
    'playback': ('loop', 'Scene playback past its last frame: loop (jump back to frame 0, '
                         'as the scene defines) or bounce (play backwards, then forwards again: '
                         'the motion stays continuous, no jump for a tracker to lose).', {}),
    'width': (640, 'Image width [px] (synthetic).', {'integer_range': _int_range(16, 4096)}),
    'height': (480, 'Image height [px] (synthetic).', {'integer_range': _int_range(16, 4096)}),
    'fx': (600.0, 'Focal length [px], both axes (synthetic and files sources; > 0).',
           {'floating_point_range': _float_range(1.0, 100000.0)}),
    'cx': (-1.0, 'Principal point x [px]; -1 = image centre (width - 1) / 2.',
           {'floating_point_range': _float_range(-1.0, 100000.0)}),
    'cy': (-1.0, 'Principal point y [px]; -1 = image centre (height - 1) / 2.',
           {'floating_point_range': _float_range(-1.0, 100000.0)}),
    'baseline': (0.10, 'Stereo baseline [m] (> 0); right camera at +x of the left one.',
                 {'floating_point_range': _float_range(0.001, 10.0)}),
    'doffs': (0.0, 'files source: cx_right - cx_left [px] (Middlebury "doffs").',
              {'floating_point_range': _float_range(-10000.0, 10000.0)}),
    'encoding': ('mono8', f'Image encoding: one of {", ".join(ENCODINGS)}.', {}),
    'ground_truth': (True, 'Publish ground truth (poses, depth, disparity, occlusion).', {}),
    'publish_depth': (True, 'With ground_truth: publish depth_truth.', {}),
    'publish_disparity': (True, 'With ground_truth: publish disparity_truth and '
                                'occlusion_truth.', {}),
    'noise_sigma': (0.0, 'Additive Gaussian image noise std [grey levels].',
                    {'floating_point_range': _float_range(0.0, 100.0)}),
    'blur_sigma': (0.0, 'Gaussian blur std [px] (0 = none).',
                   {'floating_point_range': _float_range(0.0, 20.0)}),
    'gain_right': (1.0, 'Photometric gain of the right camera relative to the left.',
                   {'floating_point_range': _float_range(0.1, 10.0)}),
    'left_frame_id': ('stereo_left_optical', 'frame_id of the left images and of the truth.', {}),
    'right_frame_id': ('stereo_right_optical', 'frame_id of the right images.', {}),
    'left_file': ('', 'files source: left image path.', {}),
    'right_file': ('', 'files source: right image path.', {}),
}

_REBUILD = {'source', 'scene', 'seed', 'width', 'height', 'fx', 'cx', 'cy', 'baseline',
            'doffs', 'encoding', 'noise_sigma', 'blur_sigma', 'gain_right', 'left_file',
            'right_file'}


def validate_parameter(name: str, value, current: Dict[str, object]) -> Optional[str]:
    """Reason a parameter value is refused, or None when acceptable (pure, for tests)."""
    if name == 'source' and value not in SOURCES:
        return f'unknown source {value!r}; choose one of: {", ".join(SOURCES)}'
    if name == 'scene' and value not in SCENES:
        return f'unknown scene {value!r}; choose one of: {", ".join(SCENES)}'
    if name == 'playback' and value not in PLAYBACKS:
        return f'unknown playback {value!r}; choose one of: {", ".join(PLAYBACKS)}'
    if name == 'encoding' and value not in ENCODINGS:
        return f'unsupported encoding {value!r}; choose one of: {", ".join(ENCODINGS)}'
    if name == 'rate' and not (math.isfinite(value) and value > 0):
        return f'rate must be > 0 Hz, got {value}'
    if name == 'fx' and not (math.isfinite(value) and value > 0):
        return f'focal length fx must be > 0 px, got {value}'
    if name == 'baseline' and not (math.isfinite(value) and value > 0):
        return f'baseline must be > 0 m, got {value}'
    if name in ('cx', 'cy') and not (value == -1.0 or value >= 0):
        return f'{name} must be -1 (centre) or >= 0 px, got {value}'
    if name in ('left_frame_id', 'right_frame_id') and not value:
        return f'{name} must not be empty'
    if name in ('left_file', 'right_file') and current.get('source') == 'files' and not value:
        return f'{name} must be set when source is files'
    return None


class SyntheticCameraNode(Node):
    """Publishes rectified stereo pairs with CameraInfo and ground truth at ``rate`` Hz."""

    def __init__(self, **kwargs) -> None:
        super().__init__('synthetic_camera', **kwargs)
        self._values: Dict[str, object] = {}
        self._dirty = True
        self._rate_dirty = False
        self.add_on_set_parameters_callback(self._on_set_parameters)
        for name, (default, desc, extra) in _PARAMS.items():
            self.declare_parameter(name, default, ParameterDescriptor(
                name=name, description=desc, **extra))
        self._values = {n: self.get_parameter(n).value for n in _PARAMS}
        self._source: Optional[SyntheticStereo] = None
        self._still: Optional[RealStereoPair] = None
        self._frame = int(self._values['start_frame'])
        self.frames_published = 0
        self.late_frames = 0
        self.caught_up_frames = 0    # rendered late, for a period the timer had skipped
        self.dropped_frames = 0      # periods the camera missed beyond catch_up_frames
        self._steady_clock = time.monotonic    # the frame grid's clock [s]
        self._warm = False  # the first frame after a rebuild loads the JIT cache: not "late"
        self.render_errors = 0
        self._pose_pubs: Dict[str, object] = {}
        # depth 1: a late reader gets the newest frame, never a backlog
        self._pub_left = self.create_publisher(Image, 'left/image_rect', 1)
        self._pub_right = self.create_publisher(Image, 'right/image_rect', 1)
        self._pub_info_l = self.create_publisher(CameraInfo, 'left/camera_info', 1)
        self._pub_info_r = self.create_publisher(CameraInfo, 'right/camera_info', 1)
        self._pub_depth = self.create_publisher(Image, 'depth_truth', 5)
        self._pub_disp = self.create_publisher(DisparityImage, 'disparity_truth', 5)
        self._pub_occ = self.create_publisher(Image, 'occlusion_truth', 5)
        self._rebuild()  # raises ValueError/FileNotFoundError with a clear message
        self._timer = None
        if self._values['trigger']:
            self.create_subscription(Empty, 'trigger', lambda _msg: self._tick(), 10)
        else:
            self._grid = FrameGrid(float(self._values['rate']),
                                   int(self._values['catch_up_frames']))
            self._timer = self.create_timer(1.0 / float(self._values['rate']), self._on_timer)
        self.get_logger().info(self._describe())
        self.diagnostics = NodeDiagnostics(self, lambda: {  # /diagnostics: topics, counters
            'frames_published': self.frames_published, 'late_frames': self.late_frames,
            'caught_up_frames': self.caught_up_frames, 'dropped_frames': self.dropped_frames,
            'render_errors': self.render_errors})

    # --- parameters -----------------------------------------------------------------------
    def _on_set_parameters(self, params) -> SetParametersResult:
        current = dict(self._values)
        for p in params:
            current[p.name] = p.value
        for p in params:
            reason = validate_parameter(p.name, p.value, current)
            if reason is not None:
                self.get_logger().warning(f'refused parameter {p.name}={p.value!r}: {reason}')
                return SetParametersResult(successful=False, reason=reason)
        if self._values:  # after construction: apply on the next tick
            for p in params:
                self._values[p.name] = p.value
                if p.name in _REBUILD:
                    self._dirty = True
                if p.name == 'rate':
                    self._rate_dirty = True
                if p.name == 'start_frame':
                    self._frame = int(p.value)
        return SetParametersResult(successful=True)

    def _camera(self) -> StereoCamera:
        v = self._values
        w, h = int(v['width']), int(v['height'])
        cx = None if v['cx'] == -1.0 else float(v['cx'])
        cy = None if v['cy'] == -1.0 else float(v['cy'])
        return StereoCamera.create(w, h, float(v['fx']), baseline=float(v['baseline']), cx=cx,
                                   cy=cy)

    def _rebuild(self) -> None:
        v = self._values
        self._dirty = False
        if v['source'] == 'synthetic':
            opts = RenderOptions(color=v['encoding'] == 'rgb8',
                                 noise_sigma=float(v['noise_sigma']),
                                 blur_sigma=float(v['blur_sigma']),
                                 gain_right=float(v['gain_right']))
            self._source = SyntheticStereo(str(v['scene']), int(v['seed']), self._camera(), opts)
            self._still = None
            for name in self._source.scene.objects:
                if name not in self._pose_pubs:
                    self._pose_pubs[name] = self.create_publisher(
                        PoseStamped, f'objects/{name}/pose_truth', 5)
        else:
            if v['source'] == 'motorcycle':
                pair = load_motorcycle()
            else:
                cam = self._camera()
                for key in ('left_file', 'right_file'):
                    if not v[key]:
                        raise ValueError(f'{key} must be set when source is files')
                pair = load_stereo_files(str(v['left_file']), str(v['right_file']), cam.fx,
                                         cam.baseline, None if v['cx'] == -1.0 else cam.cx,
                                         None if v['cy'] == -1.0 else cam.cy, float(v['doffs']))
            self._still = pair.as_gray() if v['encoding'] == 'mono8' else pair
            self._source = None
            if self._still.left.ndim == 2 and v['encoding'] == 'rgb8':
                self._still = RealStereoPair(*[np.dstack([im] * 3) for im in
                                               (self._still.left, self._still.right)],
                                             self._still.fx, self._still.cx, self._still.cy,
                                             self._still.doffs, self._still.baseline,
                                             self._still.disparity, self._still.name)

    def _describe(self) -> str:
        v = self._values
        if self._source is not None:
            c = self._source.camera
            return (f'synthetic camera: scene {v["scene"]} (seed {v["seed"]}), '
                    f'{c.width}x{c.height}'
                    f' {v["encoding"]}, fx {c.fx} px, baseline {c.baseline} m, {v["rate"]} Hz')
        s = self._still
        return (f'still stereo pair {s.name}: {s.left.shape[1]}x{s.left.shape[0]} '
                f'{v["encoding"]}, fx {s.fx} px, baseline {s.baseline} m, {v["rate"]} Hz')

    # --- publishing ---------------------------------------------------------------------
    def _infos(self, header_l: Header, header_r: Header):
        if self._source is not None:
            c = self._source.camera
            params = StereoCameraParameters(fx=c.fx, fy=c.fy, cx=c.cx, cy=c.cy,
                                            baseline=c.baseline, width=c.width, height=c.height)
        else:
            s = self._still
            # Middlebury pairs: cx_right = cx_left + doffs
            params = StereoCameraParameters(fx=s.fx, fy=s.fx, cx=s.cx, cy=s.cy,
                                            baseline=s.baseline, width=s.left.shape[1],
                                            height=s.left.shape[0], doffs=s.doffs)
        left, right = camera_info_from_parameters(params, header_l)
        right.header = header_r
        return left, right

    def _on_timer(self) -> None:
        """Free-running wake-up: render every frame the grid says is due (see FrameGrid)."""
        if self._rate_dirty:
            self._rate_dirty = False
            self._timer.cancel()
            self.destroy_timer(self._timer)
            self._timer = self.create_timer(1.0 / float(self._values['rate']), self._on_timer)
            self._grid = FrameGrid(float(self._values['rate']),
                                   int(self._values['catch_up_frames']))
        self._grid.catch_up = int(self._values['catch_up_frames'])
        if self._dirty or not self._warm:
            # the first frame after a (re)build loads the JIT cache: the grid starts after it
            self._tick()
            self._grid.reset()
            return
        render, dropped = self._grid.due(self._steady_clock())
        if dropped:
            self.dropped_frames += dropped
            self._frame += dropped * int(self._values['frame_step'])   # the scene goes on
            self.get_logger().warning(
                f'camera woken {dropped + render - 1} periods late: {dropped} frame(s) dropped '
                f'({self.dropped_frames} so far), {render - 1} rendered late',
                throttle_duration_sec=5.0)
        for k in range(render):
            if k:
                self.caught_up_frames += 1
            self._tick()

    def _tick(self) -> None:
        t0 = time.perf_counter()
        if self._dirty:
            try:
                self._warm = False
                self._rebuild()
                self.get_logger().info(self._describe())
            except (ValueError, OSError) as exc:
                self.render_errors += 1
                self.get_logger().error(f'cannot apply the new parameters: {exc}')
                return
        v = self._values
        enc = str(v['encoding'])
        truth = None
        want_depth = bool(v['ground_truth'] and v['publish_depth']
                          and self._pub_depth.get_subscription_count())
        want_disparity = bool(v['ground_truth'] and v['publish_disparity']
                              and (self._pub_disp.get_subscription_count()
                                   or self._pub_occ.get_subscription_count()))
        if self._source is not None:
            # without a truth-image subscriber the pair is rendered without them (same images;
            # no occlusion mask, no fresh truth buffers: ~4 ms CPU less per pair)
            left, right, truth = self._source.render(scene_frame(
                self._frame, self._source.scene.n_frames, str(v['playback'])),
                images_only=not (want_depth or want_disparity))
            disparity, depth, occ = (truth.get('disparity'), truth.get('depth'),
                                     truth.get('occlusion'))
            f, baseline = self._source.camera.fx, self._source.camera.baseline
        else:
            s = self._still
            left, right = s.left, s.right
            disparity, depth, occ = s.disparity, s.depth(), None
            f, baseline = s.fx, s.baseline
        # Stamped when the pair exists (after rendering), as a camera stamps its exposure: the
        # renderer's cost is the simulation's, not the camera's, and it is not counted as
        # latency of the graph downstream.
        stamp = self.get_clock().now().to_msg()
        hl = Header(stamp=stamp, frame_id=str(v['left_frame_id']))
        hr = Header(stamp=stamp, frame_id=str(v['right_frame_id']))
        info_l, info_r = self._infos(hl, hr)
        self._pub_left.publish(numpy_to_image(left, enc, hl))
        self._pub_right.publish(numpy_to_image(right, enc, hr))
        self._pub_info_l.publish(info_l)
        self._pub_info_r.publish(info_r)
        if v['ground_truth']:
            if truth is not None:
                for name, T in truth['poses'].items():
                    self._pose_pubs[name].publish(matrix_to_pose_stamped(T, hl))
            # truth images only for a subscriber (they cost more than the pair itself)
            if want_depth and depth is not None:
                self._pub_depth.publish(numpy_to_image(np.ascontiguousarray(depth, np.float32),
                                                       '32FC1', hl))
            if want_disparity and disparity is not None:
                self._pub_disp.publish(self._disparity_msg(disparity, f, baseline, hl))
                if occ is not None:
                    self._pub_occ.publish(numpy_to_image(occ.astype(np.uint8) * 255, 'mono8',
                                                         hl))
        self._frame += int(self._values['frame_step'])
        self.frames_published += 1
        dt = time.perf_counter() - t0
        warm, self._warm = self._warm, True
        if warm and self._timer is not None and dt > 1.0 / float(v['rate']):
            self.late_frames += 1
            self.get_logger().warning(
                f'frame took {1e3 * dt:.1f} ms, longer than the {1e3 / float(v["rate"]):.1f} ms '
                f'period ({self.late_frames} late of {self.frames_published})',
                throttle_duration_sec=5.0)

    @staticmethod
    def _disparity_msg(disparity: np.ndarray, f: float, baseline: float,
                       header: Header) -> DisparityImage:
        d = np.asarray(disparity, np.float32)
        ok = np.isfinite(d)
        img = np.where(ok, d, np.float32(-1.0)).astype(np.float32)
        msg = DisparityImage()
        msg.header = header
        msg.image = numpy_to_image(img, '32FC1', header)
        msg.f = float(f)
        msg.t = float(baseline)
        msg.min_disparity = 0.0
        msg.max_disparity = float(d[ok].max()) if ok.any() else 0.0
        msg.delta_d = 0.0
        msg.valid_window.x_offset = 0
        msg.valid_window.y_offset = 0
        msg.valid_window.width = int(d.shape[1])
        msg.valid_window.height = int(d.shape[0])
        return msg


def main(args=None):
    rclpy.init(args=args)
    try:
        node = SyntheticCameraNode()
    except (ParameterException, ValueError, OSError) as exc:
        # Bad parameters at start-up: a clear message and a non-zero exit code.
        print(f'[synthetic_camera] refused to start: {exc}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        sys.exit(2)
    spin_until_shutdown(node)


if __name__ == '__main__':
    main()
