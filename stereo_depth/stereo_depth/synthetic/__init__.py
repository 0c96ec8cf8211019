"""
Synthetic stereo camera: object models, camera model, texture, ray-cast renderer, scenes.

Pure numpy/numba/OpenCV (no rclpy). The offline entry point is :func:`render`::

    from stereo_depth.synthetic import render
    left, right, truth = render('peg_in_hole', 42)

``truth`` is documented in :mod:`stereo_depth.synthetic.renderer`; :func:`render` adds
``frame_index`` (wrapped), ``time`` [s], ``scene``, ``seed``, ``T_world_camera`` and the scene
extras (``contact_phase``, ``joint``, ...; see :mod:`stereo_depth.synthetic.scenes`).
"""

from __future__ import annotations

from typing import Dict, Optional, Tuple, Union

import numpy as np

from stereo_manip_tools.mesh_io import find_model, load_obj

from .camera import look_at, StereoCamera
from .real_images import load_motorcycle, load_stereo_files, RealStereoPair
from .renderer import RenderOptions, reprojection_errors, StereoRenderer
from .scenes import make_scene, Scene, SCENES

__all__ = ['render', 'SyntheticStereo', 'StereoCamera', 'RenderOptions', 'StereoRenderer',
           'Scene', 'SCENES', 'make_scene', 'look_at', 'load_motorcycle', 'load_stereo_files',
           'RealStereoPair', 'reprojection_errors']


class SyntheticStereo:
    """
    A scene bound to a camera and a renderer: ``render(frame_index)`` gives a pair + truth.

    :param scene: scene name (see ``SCENES``) or a :class:`Scene`.
    :param seed: seed of the scene's random parameters and of the texture.
    :param camera: stereo camera (default :meth:`StereoCamera.create`).
    :param options: photometric options.
    """

    def __init__(self, scene: Union[str, Scene], seed: int = 0,
                 camera: Optional[StereoCamera] = None,
                 options: Optional[RenderOptions] = None) -> None:
        self.scene = make_scene(scene, seed) if isinstance(scene, str) else scene
        self.camera = camera or StereoCamera.create()
        self.options = options or RenderOptions()
        meshes = [load_obj(find_model(n)) for n in self.scene.objects]
        self.renderer = StereoRenderer(self.camera, meshes, seed=self.scene.seed,
                                       options=self.options)

    def render(self, frame_index: int,
               images_only: bool = False) -> Tuple[np.ndarray, np.ndarray, dict]:
        """
        (left, right, truth) of frame ``frame_index`` (wraps around the scene length).

        ``images_only``: no truth images (see ``StereoRenderer.render``), same pair.
        """
        k = self.scene.frame(frame_index)
        left, right, truth = self.renderer.render(self.scene.poses(k),
                                                  noise_key=(int(frame_index) % (1 << 32),),
                                                  static=self.scene.static,
                                                  images_only=images_only)
        truth.update(self.scene.extras(k))
        truth.update({'frame_index': k, 'time': k / self.scene.fps, 'scene': self.scene.name,
                      'seed': self.scene.seed, 'T_world_camera': self.scene.T_world_camera})
        return left, right, truth


_CACHE: Dict[tuple, SyntheticStereo] = {}


def render(scene: Union[str, Scene], frame_index: int, seed: int = 0,
           camera: Optional[StereoCamera] = None, options: Optional[RenderOptions] = None
           ) -> Tuple[np.ndarray, np.ndarray, dict]:
    """
    Render frame ``frame_index`` of a built-in scene: ``(left, right, truth)``.

    Images are uint8, (H, W) mono8 or (H, W, 3) rgb8 (``options.color``). Renderers are cached
    per (scene name, seed, camera, options), so calling this in a loop is cheap.

    :raises ValueError: for an unknown scene name or invalid camera/options.
    """
    camera = camera or StereoCamera.create()
    options = options or RenderOptions()
    if isinstance(scene, Scene):
        return SyntheticStereo(scene, camera=camera, options=options).render(frame_index)
    key = (scene, int(seed), camera, options)
    if key not in _CACHE:
        if len(_CACHE) >= 8:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = SyntheticStereo(scene, seed, camera, options)
    return _CACHE[key].render(frame_index)
