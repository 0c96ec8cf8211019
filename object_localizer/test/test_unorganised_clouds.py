"""
The acquisition's observed depth image of organised and unorganised clouds.

An unorganised cloud (points scattered at random over the visible surfaces, as the process
tests' producer ``cloud_stream_peer.py`` streams) leaves chance holes in an image whose pixel
is matched to the mean point spacing; an organised (camera) cloud has one point per pixel.
Ground truth: the producer's scenes, and the same scenes as organised clouds of a 640x480
camera.
"""

import importlib.util
from pathlib import Path

import numpy as np
from object_localizer.acquisition import prepare_acquisition_scene
from object_localizer.evaluation import sample_visible_surface
from object_localizer.verification import interior_hole_rate, observe_depth, PinholeCamera
import pytest
from stereo_manip_tools.mesh_io import find_model, load_obj

# the producer's scene generator (a script beside the tests, not a module on the path)
_SPEC = importlib.util.spec_from_file_location(
    'cloud_stream_peer', Path(__file__).with_name('cloud_stream_peer.py'))
_PEER = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(_PEER)
peg_pose, scene = _PEER.peg_pose, _PEER.scene

CAMERA = PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480)


@pytest.fixture(scope='module')
def peg():
    return (load_obj(find_model('peg')),)


def _organised(points: np.ndarray, camera: PinholeCamera) -> np.ndarray:
    """Keep the nearest point per camera pixel: an organised (H, W, 3) cloud, NaN = none."""
    u = np.floor(camera.fx * points[:, 0] / points[:, 2] + camera.cx + 0.5).astype(int)
    v = np.floor(camera.fy * points[:, 1] / points[:, 2] + camera.cy + 0.5).astype(int)
    ok = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    out = np.full((camera.height, camera.width, 3), np.nan)
    order = np.argsort(-points[ok, 2])            # the nearest written last
    out[v[ok][order], u[ok][order]] = points[ok][order]
    return out


def _camera_scene(mesh, k: int, rng: np.random.Generator) -> np.ndarray:
    """Make the producer's scene ``k`` as a camera sees it: one point per pixel."""
    T = peg_pose(k)
    P = sample_visible_surface(mesh, T, 400000, seed=k)
    g = np.mgrid[-0.2:0.2:0.0005, -0.15:0.15:0.0005].reshape(2, -1).T
    table = np.column_stack([g, np.full(len(g), 0.65)])
    cloud = _organised(np.vstack([P, table]), CAMERA)
    # noise along the rays (the depth), as stereo's: the points stay on their pixels
    noise = rng.normal(scale=0.0007, size=cloud.shape[:2])
    return cloud * (1.0 + noise / cloud[..., 2])[..., None]


def test_organised_camera_clouds_have_no_chance_holes(peg):
    mesh = peg[0]
    cloud = _camera_scene(mesh, 0, np.random.default_rng(0))
    observed = observe_depth(cloud, CAMERA, max_hole_rate=np.inf)
    assert interior_hole_rate(observed.depth) < 0.01
    assert interior_hole_rate(observe_depth(cloud, CAMERA, stride=1).depth) < 0.01
    # the producer's unorganised cloud gets an image coarse enough to have as few
    sparse = scene(0, np.random.default_rng(0), mesh)
    coarse = observe_depth(sparse, CAMERA, stride=1)
    assert interior_hole_rate(coarse.depth) <= 0.01


def test_virtual_camera_carries_the_stereo_baseline(peg):
    mesh = peg[0]
    sparse = scene(0, np.random.default_rng(0), mesh)
    assert observe_depth(sparse).right is None
    observed = observe_depth(sparse, stereo_baseline=0.1)
    assert observed.camera.baseline == 0.1 and observed.right is not None
    # an intrinsics-only camera gets the baseline too; a stereo camera keeps its own
    assert observe_depth(sparse, CAMERA, stereo_baseline=0.1).camera.baseline == 0.1
    stereo = PinholeCamera(600.0, 600.0, 319.5, 239.5, 640, 480, 0.12)
    assert observe_depth(sparse, stereo, stereo_baseline=0.1).camera.baseline == 0.12
    assert prepare_acquisition_scene(sparse, stereo_baseline=0.1).observed().right is not None
    with pytest.raises(ValueError):
        observe_depth(sparse, stereo_baseline=-0.1)
