"""The committed bags are complete, consistent recordings of what their README says."""

from collections import defaultdict
from pathlib import Path

import pytest
from rclpy.serialization import deserialize_message

from stereo_manip_tools.bag_io import bag_summary, get_message_class, read_bag
from stereo_manip_tools.conversions import image_to_numpy, stamp_to_ns, \
    stereo_parameters_from_camera_info

BAGS = Path(__file__).resolve().parents[1] / 'bags'


def test_peg_in_hole_bag_is_a_synchronised_stereo_recording():
    bag = BAGS / 'peg_in_hole_320x240'
    topics, first, last = bag_summary(bag)
    assert {t: n for t, (_, n) in topics.items()} == {
        '/left/image_rect': 30, '/right/image_rect': 30, '/left/camera_info': 30,
        '/right/camera_info': 30, '/objects/peg/pose_truth': 30,
        '/objects/hole_block/pose_truth': 30}
    assert 4.0 < (last - first) / 1e9 < 9.0  # 30 frames at 5 Hz
    stamps = defaultdict(list)
    infos = {}
    for m in read_bag(bag):
        msg = deserialize_message(m.data, get_message_class(m.msgtype))
        stamps[m.topic].append(stamp_to_ns(msg.header.stamp))
        if m.topic.endswith('image_rect'):
            img = image_to_numpy(msg)
            assert img.shape == (240, 320) and img.dtype.name == 'uint8'
        if m.topic.endswith('camera_info'):
            infos[m.topic] = msg
    # every frame's six messages carry one stamp
    assert len({tuple(v) for v in stamps.values()}) == 1
    params = stereo_parameters_from_camera_info(infos['/left/camera_info'],
                                                infos['/right/camera_info'])
    assert params.fx == pytest.approx(300.0) and params.baseline == pytest.approx(0.10)
