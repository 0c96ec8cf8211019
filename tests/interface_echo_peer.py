"""
Peer process for test_interfaces_interprocess.

Echoes every stereo_manip_msgs message and answers every service, so the test exercises both
directions across two processes over DDS.

Messages on ``/roundtrip/in/<Name>`` are republished unchanged on ``/roundtrip/out/<Name>``.
Service ``/roundtrip/<Name>`` answers ``fill_message(Response, 42)`` with ``success`` set to
whether the request equalled ``fill_message(Request, 7)`` field by field.
"""

import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from stereo_manip_msgs import msg as msgs, srv as srvs
from stereo_manip_tools.robustness import spin_until_shutdown
from stereo_manip_tools.testing import fill_message

MESSAGES = ['ContactElement', 'ContactPair', 'ContactState', 'JointEstimate',
            'ImplicitPolynomial', 'TrackStatus']
SERVICES = ['CorrectTrajectory', 'EstimateJoint', 'FitImplicitPolynomial']


def main() -> None:
    rclpy.init()
    node = rclpy.create_node('interface_echo_peer')
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    keep = []
    for name in MESSAGES:
        cls = getattr(msgs, name)
        pub = node.create_publisher(cls, f'/roundtrip/out/{name}', qos)
        keep.append(node.create_subscription(cls, f'/roundtrip/in/{name}', pub.publish, qos))
    for name in SERVICES:
        cls = getattr(srvs, name)

        def answer(request, response, cls=cls):
            filled = fill_message(cls.Response, 42)
            filled.success = request == fill_message(cls.Request, 7)
            return filled
        keep.append(node.create_service(cls, f'/roundtrip/{name}', answer))
    spin_until_shutdown(node)


if __name__ == '__main__':
    main()
