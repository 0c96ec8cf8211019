"""
Producer process for the localizer's process tests: a camera-like stream of clouds.

Publishes ``/points2`` (PointCloud2, reliable, 10 Hz) of a scene with the peg moving slowly over
a table, and the peg's true pose on ``/objects/peg/pose_truth`` with the same stamp. The clouds
are the peg's and the table's visible surfaces with 0.7 mm noise (the table hidden behind the
peg removed), precomputed for 100 poses (a 10 s loop) and played in a loop (stamps keep
increasing).
"""

import time

from geometry_msgs.msg import PoseStamped
import numpy as np
from object_localizer.evaluation import sample_visible_surface
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from scipy.spatial import cKDTree
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp, xyz_to_pointcloud2
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.robustness import spin_until_shutdown
from stereo_manip_tools.transforms import make_transform, rotation_about_axis

FRAMES = 100
RATE = 10.0


def peg_pose(k: int) -> np.ndarray:
    a = 2 * np.pi * (k % FRAMES) / FRAMES
    R = rotation_about_axis([1, 0, 0], 2.3) @ rotation_about_axis([0, 0, 1], 0.3 * np.sin(a))
    return make_transform(R, [0.03 * np.cos(a), 0.02 * np.sin(a), 0.55])


def scene(k: int, rng: np.random.Generator, mesh) -> np.ndarray:
    T = peg_pose(k)
    P = sample_visible_surface(mesh, T, 15000, seed=k)
    P = P + rng.normal(scale=0.0007, size=P.shape)
    g = np.mgrid[-0.2:0.2:0.002, -0.15:0.15:0.002].reshape(2, -1).T
    table = np.column_stack([g, np.full(len(g), 0.65)])
    d, _ = cKDTree(P[:, :2] / P[:, 2:3]).query(table[:, :2] / table[:, 2:3])
    return np.vstack([P, table[d * 0.65 > 0.003]])


def main() -> None:
    rclpy.init()
    node = rclpy.create_node('cloud_stream_peer')
    qos = QoSProfile(depth=2, reliability=ReliabilityPolicy.RELIABLE)
    pub = node.create_publisher(PointCloud2, '/points2', qos)
    truth = node.create_publisher(PoseStamped, '/objects/peg/pose_truth', 10)
    mesh = load_obj(find_model('peg'))
    rng = np.random.default_rng(0)
    clouds = [scene(k, rng, mesh) for k in range(FRAMES)]
    k = 0
    t0 = time.time()

    def tick() -> None:
        nonlocal k
        header = Header(frame_id='stereo_left_optical',
                        stamp=ns_to_stamp(int((t0 + k / RATE) * 1e9)))
        pub.publish(xyz_to_pointcloud2(clouds[k % FRAMES], header))
        truth.publish(PoseStamped(header=header, pose=matrix_to_pose(peg_pose(k))))
        k += 1
    node.create_timer(1.0 / RATE, tick)
    node.get_logger().info('streaming')
    spin_until_shutdown(node)


if __name__ == '__main__':
    main()
