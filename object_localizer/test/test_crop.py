"""The tracker's compiled crops give exactly the points of their numpy definitions."""

import numpy as np
from object_localizer.crop import crop_near, crop_rays, crop_window
import pytest
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


@pytest.fixture(scope='module')
def cloud():
    """Make a float32 cloud of 80000 points [m], some NaN, some behind the sensor."""
    rng = np.random.default_rng(3)
    P = rng.uniform([-0.4, -0.3, -0.1], [0.4, 0.3, 1.2], size=(80000, 3)).astype(np.float32)
    P[rng.choice(len(P), 2000, replace=False)] = np.nan
    P[rng.choice(len(P), 500, replace=False), 1] = np.inf
    return P


def _rows(a):
    return a[np.lexsort(a.T)]


def test_crop_rays_is_the_cone_at_any_depth(cloud):
    a0, b0, rho = 0.1, -0.05, 0.08
    with np.errstate(invalid='ignore'):
        z = cloud[:, 2]
        keep = (z > 1e-6) & (np.abs(cloud[:, 0] - a0 * z) <= rho * z) & \
            (np.abs(cloud[:, 1] - b0 * z) <= rho * z)
    out = crop_rays(cloud, a0, b0, rho)
    assert out.dtype == np.float64 and 1000 < len(out) < len(cloud) / 4
    np.testing.assert_array_equal(out, cloud[keep].astype(np.float64))   # order kept


def test_crop_near_is_the_sphere_and_the_posed_box(cloud):
    pose = make_transform(rotation_about_axis([0.3, 1.0, -0.2], 0.8), [0.05, 0.02, 0.6])
    lo, hi = np.array([-0.06, -0.03, -0.04]), np.array([0.05, 0.04, 0.03])
    centre, reach = pose[:3, 3] + [0.01, 0.0, 0.0], 0.07
    P = cloud.astype(np.float64)
    with np.errstate(invalid='ignore'):
        local = (P - pose[:3, 3]) @ pose[:3, :3]
        keep = (np.sum((P - centre) ** 2, axis=1) <= reach ** 2) & \
            np.all((local >= lo) & (local <= hi), axis=1)
    out = crop_near(cloud, centre, reach, pose, lo, hi)
    assert 30 < len(out) < keep.size / 100
    # the same points (a point on a face may fall either way by rounding: none here)
    np.testing.assert_allclose(_rows(out), _rows(P[keep]), atol=0)


def test_crop_window_is_the_normalised_image_window(cloud):
    lo, hi = np.array([-0.2, -0.1]), np.array([0.05, 0.15])
    with np.errstate(invalid='ignore', divide='ignore'):
        a = cloud[:, :2].astype(np.float64) / cloud[:, 2:3].astype(np.float64)
        keep = (cloud[:, 2] > 1e-6) & np.all((a >= lo) & (a <= hi), axis=1)
    out = crop_window(cloud, lo, hi)
    assert len(out) > 1000
    np.testing.assert_array_equal(out, cloud[keep].astype(np.float64))


def test_empty_clouds_give_empty_crops():
    empty = np.zeros((0, 3), dtype=np.float32)
    assert crop_rays(empty, 0.0, 0.0, 0.1).shape == (0, 3)
    assert crop_window(empty, np.zeros(2), np.ones(2)).shape == (0, 3)
    assert crop_near(empty, np.zeros(3), 1.0, np.eye(4), -np.ones(3), np.ones(3)).shape == (0, 3)
