"""Offline export of synthetic sequences and the real still-image sources."""

import csv

import cv2
import numpy as np
import pytest

from stereo_depth.synthetic import load_motorcycle, load_stereo_files, render
from stereo_depth.synthetic.export import main, parse_frames


def test_export_writes_images_truth_and_poses(tmp_path):
    assert main(['--scene', 'prismatic_pair', '--frames', '3:9:3', '--out', str(tmp_path),
                 '--seed', '2']) == 0
    left = cv2.imread(str(tmp_path / 'left_000006.png'), cv2.IMREAD_UNCHANGED)
    ref_left, _, ref_truth = render('prismatic_pair', 6, seed=2)
    np.testing.assert_array_equal(left, ref_left)
    t = np.load(tmp_path / 'truth_000006.npz')
    np.testing.assert_array_equal(t['depth'], ref_truth['depth'])
    with open(tmp_path / 'poses.csv', newline='') as fh:
        rows = list(csv.DictReader(fh))
    assert {r['frame'] for r in rows} == {'3', '6'}
    carriage = [r for r in rows if r['frame'] == '6' and r['object'] == 'slider_carriage'][0]
    np.testing.assert_allclose([float(carriage[k]) for k in 'xyz'],
                               ref_truth['poses']['slider_carriage'][:3, 3], atol=1e-8)


def test_export_refuses_bad_frames(tmp_path):
    assert main(['--frames', '5:2', '--out', str(tmp_path)]) == 2
    with pytest.raises(ValueError):
        parse_frames('a:b')


def test_motorcycle_pair_and_calibration():
    pair = load_motorcycle()
    assert pair.left.shape == (500, 741, 3) and pair.disparity.shape == (500, 741)
    assert pair.P_right[0, 3] == pytest.approx(-994.978 * 0.193001)
    assert pair.K_right[0, 2] - pair.K_left[0, 2] == pytest.approx(31.086)
    z = pair.depth()
    ok = np.isfinite(z)
    assert ok.mean() > 0.9
    # Z = f B / (d + doffs): the motorcycle is 2-5 m away.
    assert 1.5 < np.nanmedian(z) < 5.0
    # GT consistency: left pixel colour matches the right pixel at x - d on textured areas.
    g = pair.as_gray()
    v, u = np.nonzero(ok & (np.arange(741)[None, :] > 80))
    ur = np.round(u - pair.disparity[v, u]).astype(int)
    diff = np.abs(g.left[v, u].astype(int) - g.right[v, ur].astype(int))
    assert np.median(diff) < 10


def test_stereo_files_round_trip_and_errors(tmp_path):
    left, right, _ = render('primitives', 0, seed=1)
    cv2.imwrite(str(tmp_path / 'l.png'), left)
    cv2.imwrite(str(tmp_path / 'r.png'), right)
    pair = load_stereo_files(str(tmp_path / 'l.png'), str(tmp_path / 'r.png'), fx=600.0,
                             baseline=0.1)
    np.testing.assert_array_equal(pair.left, left)
    assert pair.cx == pytest.approx(319.5)
    with pytest.raises(FileNotFoundError, match='nothere'):
        load_stereo_files(str(tmp_path / 'nothere.png'), str(tmp_path / 'r.png'), 600.0, 0.1)
    with pytest.raises(ValueError, match='fx'):
        load_stereo_files(str(tmp_path / 'l.png'), str(tmp_path / 'r.png'), 0.0, 0.1)
