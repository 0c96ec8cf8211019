"""The benchmark writer computes `met` from the measured value."""

import json
import math

import numpy as np
import pytest

from stereo_manip_tools.bench_report import goal, write_report


def test_goal_met_is_computed():
    assert goal('fps', 30, '>=', 31.0)['met']
    assert not goal('fps', 30, '>=', 29.9)['met']
    assert not goal('err', 1.0, '<', math.nan)['met']
    with pytest.raises(ValueError):
        goal('x', 1, '=>', 1)


def test_write_report(tmp_path):
    path = write_report('camera_test', [goal('fps', 30, '>=', 40)], directory=tmp_path,
                        raw=np.arange(3), scalar=np.float32(1.5))
    data = json.loads(path.read_text())
    assert data['goals'][0]['met'] is True
    assert data['raw'] == [0, 1, 2] and data['scalar'] == 1.5
    assert data['machine']['cpu_count'] >= 1
