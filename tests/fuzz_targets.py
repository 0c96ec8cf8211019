"""
Every node's subscribers under fuzzing: the good input of each cycle and its checked output.

Shared by ``tests/test_fuzz_nodes.py`` (a few cycles per node) and ``bench/reliability.py``
(>= 1000 malformed messages per node). Each target's ``check`` tests the *output* for the good
input against what it must be (pose against the true pose, disparity against the true shift,
degree and distance of a sphere fit, contact-corrected pose against the hole axis, joint type
and axis), not only that the node is alive.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any, Dict, List, Optional, Tuple

import numpy as np

from stereo_manip_tools.fuzzing import FuzzTarget, malformed_camera_info, malformed_image, \
    malformed_pointcloud2, malformed_pose_stamped

BASE_NS = 1_700_000_000 * 10**9        # stamps of the good input: base + k * period


def _header(k: int, frame: str = 'stereo_left_optical', period_ns: int = 10**8) -> Any:
    from std_msgs.msg import Header
    from stereo_manip_tools.conversions import ns_to_stamp
    return Header(stamp=ns_to_stamp(BASE_NS + k * period_ns), frame_id=frame)


def _stamp_ns(msg: Any) -> int:
    from stereo_manip_tools.conversions import stamp_to_ns
    return stamp_to_ns(msg.header.stamp)


def _latest_with_stamp(msgs: List[Any], stamp: int) -> Optional[Any]:
    for m in reversed(msgs):
        if _stamp_ns(m) == stamp:
            return m
    return None


# --- object_localizer ---------------------------------------------------------------------

LOCALIZER_MODEL = 'link_arm'


@lru_cache(maxsize=1)
def _localizer_scene() -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    from object_localizer.evaluation import sample_visible_surface
    from object_localizer.localization import prepare_model
    from stereo_manip_tools.mesh_io import find_model, load_obj
    from stereo_manip_tools.transforms import make_transform, rotation_about_axis
    arm = load_obj(find_model(LOCALIZER_MODEL))
    T = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 0.9), [0.03, -0.02, 0.7])
    points = sample_visible_surface(arm, T, 6000, seed=7)
    points += np.random.default_rng(7).normal(scale=0.0005, size=points.shape)
    return T, points, prepare_model(arm).points


def localizer_target() -> FuzzTarget:
    from geometry_msgs.msg import PoseStamped
    from sensor_msgs.msg import PointCloud2
    from stereo_manip_tools.transforms import quaternion_from_matrix
    from stereo_manip_tools.conversions import xyz_to_pointcloud2

    T, points, _ = _localizer_scene()
    initial = [float(v) for v in T[:3, 3]] + [float(v) for v in quaternion_from_matrix(T[:3, :3])]

    def good(k: int) -> List[Tuple[str, Any]]:
        return [('/points2', xyz_to_pointcloud2(points, _header(k)))]

    def check(received: Dict[str, List[Any]], k: int) -> Optional[str]:
        from object_localizer.evaluation import add_s
        from stereo_manip_tools.conversions import pose_to_matrix
        T_true, _, model_points = _localizer_scene()
        msg = _latest_with_stamp(received['/objects/link_arm/pose'], BASE_NS + k * 10**8)
        if msg is None:
            return 'no pose for the good cloud'
        err = add_s(pose_to_matrix(msg.pose), T_true, model_points)
        return None if err < 0.003 else f'pose ADD-S {err * 1e3:.2f} mm (> 3 mm)'

    return FuzzTarget(
        'object_localizer', 'object_localizer', 'object_localizer_node', 'object_localizer',
        ['-p', f'models:=[{LOCALIZER_MODEL}]',
         '-p', 'initial_poses:=[' + ','.join(repr(v) for v in initial) + ']'],
        {'/points2': (PointCloud2, malformed_pointcloud2())}, good,
        {'/objects/link_arm/pose': PoseStamped}, check, timeout=30.0, pacing=0.05)


# --- ip_modeler -----------------------------------------------------------------------------

SPHERE_RADIUS = 0.05


@lru_cache(maxsize=1)
def _sphere_points() -> np.ndarray:
    rng = np.random.default_rng(11)
    v = rng.normal(size=(1500, 3))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v = v[v[:, 2] < 0.3]                                  # the side facing the camera
    return v * SPHERE_RADIUS + [0.0, 0.0, 0.5]


def ip_modeler_target() -> FuzzTarget:
    from sensor_msgs.msg import PointCloud2
    from stereo_manip_msgs.msg import ImplicitPolynomial
    from stereo_manip_tools.conversions import xyz_to_pointcloud2

    def good(k: int) -> List[Tuple[str, Any]]:
        return [('/cloud', xyz_to_pointcloud2(_sphere_points(), _header(k)))]

    def check(received: Dict[str, List[Any]], k: int) -> Optional[str]:
        msg = _latest_with_stamp(received['/implicit_polynomial'], BASE_NS + k * 10**8)
        if msg is None:
            return 'no implicit polynomial for the good cloud'
        if msg.degree != 2 or not msg.rms_distance < 2e-4:
            return f'sphere fit: degree {msg.degree}, RMS distance {msg.rms_distance} m'
        return None

    return FuzzTarget(
        'ip_modeler', 'ip_modeler', 'ip_modeler_node', 'ip_modeler',
        ['-p', 'input_qos:=reliable', '-p', 'max_degree:=4', '-p', 'mesh_resolution:=16'],
        {'/cloud': (PointCloud2, malformed_pointcloud2(2000))}, good,
        {'/implicit_polynomial': ImplicitPolynomial}, check, timeout=30.0, pacing=0.05)


# --- contact_correction ---------------------------------------------------------------------

def _insertion_pose(k: int) -> np.ndarray:
    """Place a peg 1-4 cm deep in the hole_block (identity pose), with 1 mm / 0.5 deg of noise."""
    from stereo_manip_tools.transforms import make_transform, rotation_about_axis
    rng = np.random.default_rng(k)
    w = rng.normal(size=3) * np.deg2rad(0.5)
    z = -0.01 - 0.03 * ((k * 7919) % 100) / 100.0
    return make_transform(rotation_about_axis(w, np.linalg.norm(w)),
                          np.array([0.0, 0.0, z]) + rng.normal(size=3) * 1e-3)


def contact_target() -> FuzzTarget:
    from geometry_msgs.msg import PoseStamped
    from stereo_manip_tools.conversions import matrix_to_pose

    def good(k: int) -> List[Tuple[str, Any]]:
        fixed = PoseStamped(header=_header(k, 'world'), pose=matrix_to_pose(np.eye(4)))
        moving = PoseStamped(header=_header(k, 'world'), pose=matrix_to_pose(_insertion_pose(k)))
        return [('/fixed_pose', fixed), ('/moving_pose', moving)]

    def check(received: Dict[str, List[Any]], k: int) -> Optional[str]:
        from stereo_manip_tools.conversions import pose_to_matrix
        msg = _latest_with_stamp(received['/corrected_pose'], BASE_NS + k * 10**8)
        if msg is None:
            return 'no corrected pose for the good pose'
        Tc, T = pose_to_matrix(msg.pose), _insertion_pose(k)
        # in the hole: the rotation and the sideways offset are corrected away, depth kept
        if not (np.allclose(Tc[:3, :3], np.eye(3), atol=1e-6)
                and np.allclose(Tc[:2, 3], 0.0, atol=1e-6)
                and abs(Tc[2, 3] - T[2, 3]) < 1e-9):
            return f'pose not corrected onto the hole axis: {Tc[:3, 3]}'
        return None

    return FuzzTarget(
        'contact_correction', 'contact_correction', 'contact_correction_node',
        'contact_correction',
        ['-p', 'moving_object:=peg', '-p', 'fixed_object:=hole_block',
         '-p', 'tolerance:=0.004', '-p', 'penetration_tolerance:=0.004'],
        {'/moving_pose': (PoseStamped, malformed_pose_stamped()),
         '/fixed_pose': (PoseStamped, malformed_pose_stamped())}, good,
        {'/corrected_pose': PoseStamped}, check, timeout=20.0, pacing=0.01, good_gap=0.2)


# --- joint_estimator ------------------------------------------------------------------------

JOINT_POSES_PER_CYCLE = 16      # enough motion for an axis even with a few outliers
JOINT_AXIS = np.array([0.0, 0.0, 1.0])
JOINT_POINT = np.array([0.05, 0.0, 0.0])


def _joint_pair(i: int) -> Tuple[np.ndarray, np.ndarray]:
    """Link B fixed at 0.6 m; link A turning about B's z axis through JOINT_POINT."""
    from stereo_manip_tools.transforms import make_transform, rotation_about_axis
    T_b = make_transform(rotation_about_axis([1.0, 0.0, 0.0], 0.3), [0.0, 0.0, 0.6])
    theta = 1.0 * np.sin(0.4 * i)      # +-57 deg within every 16 poses
    R = rotation_about_axis(JOINT_AXIS, theta)
    T_rel = make_transform(R, JOINT_POINT - R @ JOINT_POINT + [0.0, 0.0, 0.0])
    T_rel = T_rel @ make_transform(np.eye(3), [0.1, 0.0, 0.0])
    return T_b @ T_rel, T_b


def joint_target() -> FuzzTarget:
    from geometry_msgs.msg import PoseStamped
    from stereo_manip_msgs.msg import JointEstimate
    from stereo_manip_tools.conversions import matrix_to_pose

    n = JOINT_POSES_PER_CYCLE

    def good(k: int) -> List[Tuple[str, Any]]:
        out = []
        for j in range(n):
            i = k * n + j
            T_a, T_b = _joint_pair(i)
            h = _header(i, 'world', period_ns=10**8 // n)
            out += [('/link_a_pose', PoseStamped(header=h, pose=matrix_to_pose(T_a))),
                    ('/link_b_pose', PoseStamped(header=h, pose=matrix_to_pose(T_b)))]
        return out

    def check(received: Dict[str, List[Any]], k: int) -> Optional[str]:
        from stereo_manip_tools.conversions import vector3_to_numpy
        stamp = BASE_NS + (k * n + n - 1) * (10**8 // n)
        msg = _latest_with_stamp(received['/joint_estimate'], stamp)
        if msg is None:
            return 'no joint estimate for the newest good pose'
        axis = vector3_to_numpy(msg.axis_in_b)
        angle = np.degrees(np.arccos(min(1.0, abs(axis @ JOINT_AXIS)
                                         / max(np.linalg.norm(axis), 1e-12))))
        if msg.joint_type != JointEstimate.REVOLUTE or angle > 2.0:
            return f'joint type {msg.joint_type}, axis error {angle:.2f} deg'
        return None

    return FuzzTarget(
        'joint_estimator', 'joint_estimator', 'joint_estimator_node', 'joint_estimator',
        ['-p', 'min_poses:=6', '-p', 'estimate_every:=1', '-p', 'window_size:=40',
         '-p', 'joint_type:=revolute'],
        {'/link_a_pose': (PoseStamped, malformed_pose_stamped()),
         '/link_b_pose': (PoseStamped, malformed_pose_stamped())}, good,
        {'/joint_estimate': JointEstimate}, check, timeout=20.0, pacing=0.01)


# --- stereo_depth ---------------------------------------------------------------------------

STEREO_SHIFT = 8            # true disparity [px] of the good pair
STEREO_SIZE = (64, 96)      # height, width


@lru_cache(maxsize=1)
def _stereo_images() -> Tuple[np.ndarray, np.ndarray]:
    import cv2
    rng = np.random.default_rng(3)
    h, w = STEREO_SIZE
    tex = cv2.GaussianBlur((rng.random((h, w + STEREO_SHIFT)) * 255).astype(np.uint8), (3, 3),
                           0)
    left = np.ascontiguousarray(tex[:, :w])
    right = np.ascontiguousarray(tex[:, STEREO_SHIFT:])    # right(x - d) = left(x): d
    return left, right


def stereo_target() -> FuzzTarget:
    from hypothesis import strategies as st
    from sensor_msgs.msg import CameraInfo, Image
    from stereo_msgs.msg import DisparityImage
    from stereo_manip_tools.conversions import camera_info_from_parameters, numpy_to_image, \
        StereoCameraParameters

    h, w = STEREO_SIZE
    params = StereoCameraParameters(fx=100.0, fy=100.0, cx=w / 2, cy=h / 2, baseline=0.1,
                                    width=w, height=h)

    def good(k: int) -> List[Tuple[str, Any]]:
        left, right = _stereo_images()
        hdr = _header(k)
        li, ri = camera_info_from_parameters(params, hdr)
        return [('/left/camera_info', li), ('/right/camera_info', ri),
                ('/left/image_rect', numpy_to_image(left, 'mono8', hdr)),
                ('/right/image_rect', numpy_to_image(right, 'mono8', hdr))]

    def check(received: Dict[str, List[Any]], k: int) -> Optional[str]:
        from stereo_manip_tools.conversions import image_to_numpy
        msg = _latest_with_stamp(received['/disparity'], BASE_NS + k * 10**8)
        if msg is None:
            return 'no disparity for the good pair'
        d = image_to_numpy(msg.image)[8:-8, 24:-8]
        d = d[d >= msg.min_disparity]
        if d.size < 0.5 * (h - 16) * (w - 32):
            return f'only {d.size} valid disparities'
        med = float(np.median(d))
        return None if abs(med - STEREO_SHIFT) < 0.5 else f'median disparity {med}'

    image = malformed_image()
    info = malformed_camera_info()

    def same_stamp_pair(left: Any, right: Any) -> List[Tuple[str, Any]]:
        right.header = left.header
        return [('/left/image_rect', left), ('/right/image_rect', right)]

    item = st.one_of(
        st.tuples(st.sampled_from(['/left/image_rect', '/right/image_rect']), image).map(
            lambda x: [x]),
        st.tuples(st.sampled_from(['/left/camera_info', '/right/camera_info']), info).map(
            lambda x: [x]),
        st.builds(same_stamp_pair, image, image))
    burst = st.lists(item, min_size=1, max_size=6).map(lambda xs: [m for x in xs for m in x])
    return FuzzTarget(
        'stereo_depth', 'stereo_depth', 'stereo_depth_node', 'stereo_depth_node',
        ['-p', 'input_qos:=reliable', '-p', 'max_disparity:=16',
         '-p', 'method:=block_matching'],
        {'/left/image_rect': (Image, image), '/right/image_rect': (Image, image),
         '/left/camera_info': (CameraInfo, info), '/right/camera_info': (CameraInfo, info)},
        good, {'/disparity': DisparityImage}, check, timeout=20.0, pacing=0.02,
        burst_strategy=burst)


TARGETS = {'object_localizer': localizer_target, 'ip_modeler': ip_modeler_target,
           'contact_correction': contact_target, 'joint_estimator': joint_target,
           'stereo_depth': stereo_target}
