"""
Acceptance (#15).

The live graph, every node its own process, broadcasts the corrected peg pose on /tf -- in a tree
that also holds the static camera mount and the frame of contact_state -- and every node publishes
/diagnostics.

The peg_in_hole graph of the demo (synthetic camera in trigger mode -> stereo_depth_node ->
object_localizer_node -> contact_correction_node), with the camera mounted on `world`, plus a
joint_estimator_node and an ip_modeler_node (idle: their diagnostics must still come).
"""

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Empty
from stereo_manip_bringup.demo import NodeSpec, STAGES
from stereo_manip_msgs.msg import ContactState
from stereo_manip_tools.conversions import pose_to_matrix, stamp_to_ns
from stereo_manip_tools.processes import ExecutableProcess
from stereo_manip_tools.testing import spin_until
from stereo_manip_tools.tf import TransformListener
from stereo_manip_tools.transforms import make_transform, matrix_from_quaternion

MOUNT = [0.1, -0.2, 1.2, -0.5, 0.5, -0.5, 0.5]     # camera 1.2 m up, looking along world +x


def graph():
    nodes = STAGES['peg_in_hole']().nodes
    for spec in nodes:
        if spec.executable == 'stereo_depth_node':
            spec.parameters.update(camera_mount_parent='world', camera_mount_pose=MOUNT)
    nodes.append(NodeSpec('joint_estimator', 'joint_estimator_node', 'joint_estimator', {},
                          {'link_a_pose': '/objects/link_arm/pose',
                           'link_b_pose': '/objects/link_base/pose'}))
    nodes.append(NodeSpec('ip_modeler', 'ip_modeler_node', 'ip_modeler',
                          {'input_qos': 'reliable'}, {'cloud': '/objects/peg/cloud'}))
    return nodes


@pytest.mark.process
def test_corrected_peg_on_tf_and_diagnostics_from_every_node(ros_node):
    node = ros_node
    listener = TransformListener(node)
    reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
    corrected, states, diagnostics = [], [], {}
    node.create_subscription(PoseStamped, '/objects/peg/pose_corrected', corrected.append,
                             reliable)
    node.create_subscription(ContactState, '/contact_state', states.append, reliable)

    def on_diagnostics(msg):
        for status in msg.status:
            diagnostics.setdefault(status.name.split(':')[0], []).append(status)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diagnostics, 50)
    trigger = node.create_publisher(Empty, '/camera_trigger', 10)
    specs = graph()
    procs = [ExecutableProcess(s.package, s.executable, (), s.ros_args()) for s in specs]
    try:
        for spec, proc in zip(specs, procs):
            assert proc.wait_for_node(node, spec.node_name, 120.0), \
                f'{spec.node_name} did not start:\n{proc.output()[-3000:]}'
        assert spin_until(node, lambda: trigger.get_subscription_count() > 0, 30.0)
        spin_until(node, lambda: False, 1.0)

        def peg_on_tf() -> bool:
            stamp = listener.stamp_of('peg_corrected')
            return stamp is not None and any(stamp_to_ns(m.header.stamp) == stamp
                                             for m in corrected)
        for _ in range(6):                                   # a few frames through the graph
            trigger.publish(Empty())
            if spin_until(node, peg_on_tf, 40.0):
                break
        assert peg_on_tf(), (f'no peg_corrected on /tf (frames: {listener.frames()}, '
                             f'{len(corrected)} corrected poses)\n'
                             + '\n'.join(p.output()[-1500:] for p in procs))
        # the transform is the corrected pose message of the same stamp, in the camera frame
        stamp = listener.stamp_of('peg_corrected')
        msg = next(m for m in corrected if stamp_to_ns(m.header.stamp) == stamp)
        parent, T_tf, _, _ = listener.edges['peg_corrected']
        assert parent == msg.header.frame_id == 'stereo_left_optical'
        assert np.allclose(T_tf, pose_to_matrix(msg.pose), atol=1e-9)
        # raw poses as <name>; the mount is static; contact_state's frame is in the same tree
        # raw and corrected poses reach /tf from two nodes: the raw one may arrive later
        assert spin_until(node, lambda: listener.can_transform('peg', 'peg_corrected'), 5.0), \
            listener.frames()
        T_mount = make_transform(matrix_from_quaternion(MOUNT[3:]), MOUNT[:3])
        T_w_cam, _ = listener.lookup('world', 'stereo_left_optical')
        assert np.allclose(T_w_cam, T_mount, atol=1e-9)
        assert spin_until(node, lambda: bool(states), 20.0)
        frame = states[-1].header.frame_id
        T_w_pc, _ = listener.lookup(frame, 'peg_corrected')      # hole_block -> peg_corrected
        T_w_h, _ = listener.lookup('world', frame)
        T_w_p, _ = listener.lookup('world', 'peg_corrected')
        assert np.allclose(T_w_h @ T_w_pc, T_w_p, atol=1e-9)
        names = [s.node_name for s in specs]
        assert spin_until(node, lambda: all(n in diagnostics for n in names), 15.0), \
            f'diagnostics from {sorted(diagnostics)}; expected {names}'

        # each node reports its counters at ~1 Hz; the topics in the graph have rates
        for name in names:
            tasks = {s.name for s in diagnostics[name]}
            assert f'{name}: counters' in tasks, tasks

        def keys(name):
            return {kv.key for s in diagnostics.get(name, []) for kv in s.values}
        # rates and stamp ages of what went through the graph, the localizer's track states
        assert spin_until(node, lambda: {'objects/peg/pose_corrected rate [Hz]',
                                         'objects/peg/pose_corrected stamp age p95 [s]',
                                         'objects/peg/pose rate [Hz]'}
                          <= keys('contact_correction'), 5.0), keys('contact_correction')
        # each node reports at 1 Hz: the report in hand may predate the first pose, wait for one
        assert spin_until(node, lambda: {'points2 rate [Hz]', 'objects/peg/pose stamp age max [s]'}
                          <= keys('object_localizer'), 5.0), keys('object_localizer')
        assert spin_until(node, lambda: {'disparity rate [Hz]', 'left/image_rect mean rate [Hz]'}
                          <= keys('stereo_depth_node'), 5.0), keys('stereo_depth_node')
        assert 'peg state' in keys('object_localizer')
    finally:
        for proc in procs:
            proc.stop()
