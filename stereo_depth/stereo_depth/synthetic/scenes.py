"""
Built-in scenes: object poses per frame, deterministic by seed (pure numpy).

World frame: the table top is the plane z = 0, +z up (metres). Every scene owns a fixed left
camera pose ``T_world_camera`` (optical frame, from :func:`look_at`) and gives, per frame,
each object's world pose; :meth:`Scene.poses` returns them in the left optical frame.
``frame_index`` wraps around ``n_frames`` so a scene can loop forever.

Scenes (``SCENES``):

* ``peg_in_hole``: the peg approaches the ``hole_block`` tilted, touches its top face with a
  vertex (vertex-face), rolls onto an edge (edge-face), onto its bottom face (face-face), slides
  over the hole and is inserted along a straight line (chapter Fig. 7-9). ``contact_phase`` per
  frame: none, vertex_face, edge_face, face_face, aligned, inserted.
* ``peg_in_slot``: the peg is lowered into the slot of ``slot_block`` (zero clearance) and slides
  along it. Phases: none, in_slot (walls), in_slot_floor (walls and floor).
* ``revolute_pair``: ``link_arm`` rotates about the revolute joint on ``link_base`` while the
  base moves (chapter Fig. 12-13).
* ``prismatic_pair``: ``slider_carriage`` slides on a moving ``slider_base``.
* ``spherical_pair``: ``ball_link`` turns about the ball joint of a moving ``socket_base``.
* ``primitives``: cube, sphere, cylinder, torus and superquadric turning slowly on the table.

Joint scenes report ``joint`` truth per frame: type, base/child names, axis and point (or
centre) in both link frames, and the joint coordinate q (rad or m) or rotation vector.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Callable, Dict, Tuple

import numpy as np

from stereo_manip_tools.transforms import (
    invert_transform, make_transform, rotation_about_axis)

from .camera import look_at

__all__ = ['Scene', 'make_scene', 'SCENES']

SCENES: Tuple[str, ...] = ('peg_in_hole', 'peg_in_slot', 'revolute_pair', 'prismatic_pair',
                           'spherical_pair', 'primitives')


def _rx(a: float) -> np.ndarray:
    return rotation_about_axis(np.array([1.0, 0.0, 0.0]), a)


def _ry(a: float) -> np.ndarray:
    return rotation_about_axis(np.array([0.0, 1.0, 0.0]), a)


def _rz(a: float) -> np.ndarray:
    return rotation_about_axis(np.array([0.0, 0.0, 1.0]), a)


def _smooth(s: float) -> float:
    """Smoothstep 0 -> 1 on s in [0, 1] (zero velocity at both ends)."""
    s = min(max(s, 0.0), 1.0)
    return s * s * (3.0 - 2.0 * s)


@dataclass
class Scene:
    """
    A built-in scene.

    :ivar name: scene name (one of ``SCENES``).
    :ivar objects: model names in render order (``object_id`` order of the truth).
    :ivar n_frames: frames in one loop; frame indices wrap around.
    :ivar fps: nominal frame rate [Hz] (time of frame k is k / fps).
    :ivar T_world_camera: left optical frame pose in the world frame (4x4).
    :ivar seed: the seed the scene's random parameters were drawn with.
    :ivar static: objects whose world pose never changes (rendered once and cached).
    """

    name: str
    objects: Tuple[str, ...]
    n_frames: int
    fps: float
    T_world_camera: np.ndarray
    seed: int
    _world: Callable[[int], Tuple[Dict[str, np.ndarray], dict]] = field(repr=False)
    static: Tuple[str, ...] = ()

    def frame(self, frame_index: int) -> int:
        """Frame index wrapped into [0, n_frames)."""
        return int(frame_index) % self.n_frames

    def world_poses(self, frame_index: int) -> Dict[str, np.ndarray]:
        """``{name: T_world_object}`` at a frame."""
        return self._world(self.frame(frame_index))[0]

    def extras(self, frame_index: int) -> dict:
        """Scene-specific truth (contact phase, joint parameters) at a frame."""
        return self._world(self.frame(frame_index))[1]

    def poses(self, frame_index: int) -> Dict[str, np.ndarray]:
        """``{name: T_left_object}``: object poses in the left optical frame."""
        T_cw = invert_transform(self.T_world_camera)
        return {n: T_cw @ T for n, T in self.world_poses(frame_index).items()}


def _peg_in_hole(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    theta = math.radians(rng.uniform(15.0, 25.0))   # tilt about the peg's y axis
    phi = math.radians(rng.uniform(10.0, 18.0))     # tilt about the peg's x axis
    yaw = rng.uniform(-0.4, 0.4)                    # block yaw on the table
    p_v = np.array([0.06 + rng.uniform(-0.005, 0.005), -0.035 + rng.uniform(-0.005, 0.005), 0.0])
    y_c = rng.uniform(-0.015, 0.015)
    T_wb = make_transform(_rz(yaw), [0.0, 0.0, 0.08])    # block top face centre in the world
    c_v = np.array([0.02, -0.02, 0.0])      # lowest vertex (peg frame) when theta, phi > 0
    c_e = np.array([0.02, 0.0, 0.0])        # midpoint of the lowest edge when phi = 0
    c_f = np.zeros(3)                       # bottom face centre

    def peg(R: np.ndarray, c: np.ndarray, p: np.ndarray) -> np.ndarray:
        """Block-frame peg pose with peg point c at block point p."""
        return make_transform(R, p - R @ c)

    n_a, n_b1, n_b2, n_c1, n_c2, n_d, n_e, n_f = 30, 20, 25, 20, 25, 45, 45, 15
    p_v2 = p_v + np.array([-0.006, 0.010, 0.0])
    R_e = _ry(theta)
    p_e0 = p_v2 + R_e @ (c_e - c_v)
    p_e1 = np.array([0.06, y_c, 0.0])
    p_f0 = p_e1 - c_e                       # bottom face centre after rolling onto the face
    depth = 0.06
    bounds = np.cumsum([n_a, n_b1, n_b2, n_c1, n_c2, n_d, n_e, n_f])

    def world(k: int):
        if k < bounds[0]:
            s = _smooth(k / (n_a - 1))
            T, phase = peg(_ry(theta) @ _rx(phi), c_v,
                           p_v + (1 - s) * np.array([0.03, 0.0, 0.10])), 'none'
            if s >= 1.0:
                phase = 'vertex_face'
        elif k < bounds[1]:
            s = _smooth((k - bounds[0] + 1) / n_b1)
            T, phase = peg(_ry(theta) @ _rx(phi), c_v, p_v + s * (p_v2 - p_v)), 'vertex_face'
        elif k < bounds[2]:
            a = phi * (1 - _smooth((k - bounds[1] + 1) / n_b2))
            T = peg(_ry(theta) @ _rx(a), c_v, p_v2)
            phase = 'vertex_face' if a > 0 else 'edge_face'
        elif k < bounds[3]:
            s = _smooth((k - bounds[2] + 1) / n_c1)
            T, phase = peg(R_e, c_e, p_e0 + s * (p_e1 - p_e0)), 'edge_face'
        elif k < bounds[4]:
            b = theta * (1 - _smooth((k - bounds[3] + 1) / n_c2))
            T = peg(_ry(b), c_e, p_e1)
            phase = 'edge_face' if b > 0 else 'face_face'
        elif k < bounds[5]:
            s = _smooth((k - bounds[4] + 1) / n_d)
            T = peg(np.eye(3), c_f, (1 - s) * p_f0)
            phase = 'face_face' if s < 1.0 else 'aligned'
        elif k < bounds[6]:
            s = (k - bounds[5] + 1) / n_e   # constant speed: a straight insertion
            T, phase = peg(np.eye(3), c_f, np.array([0.0, 0.0, -depth * s])), 'inserted'
        else:
            T, phase = peg(np.eye(3), c_f, np.array([0.0, 0.0, -depth])), 'inserted'
        poses = {'table': np.eye(4), 'hole_block': T_wb, 'peg': T_wb @ T}
        return poses, {'contact_phase': phase, 'T_block_peg': T}

    cam = look_at(T_wb[:3, 3] + np.array([0.05, -0.42, 0.45]), T_wb[:3, 3] + [0, 0, 0.02])
    return Scene('peg_in_hole', ('table', 'hole_block', 'peg'), int(bounds[-1]), 30.0, cam,
                 seed, world, static=('table', 'hole_block'))


def _peg_in_slot(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-0.5, 0.5)
    x0 = rng.uniform(0.045, 0.055)
    T_wb = make_transform(_rz(yaw), [0.0, 0.0, 0.08])
    n_a, n_b, n_c, n_d = 30, 40, 60, 15
    depth = 0.04

    def world(k: int):
        if k < n_a:
            s = _smooth(k / (n_a - 1))
            p = np.array([x0, 0.0, 0.10 * (1 - s)])
            phase = 'none' if s < 1.0 else 'in_slot'
        elif k < n_a + n_b:
            s = (k - n_a + 1) / n_b
            p = np.array([x0, 0.0, -depth * s])
            phase = 'in_slot' if s < 1.0 else 'in_slot_floor'
        elif k < n_a + n_b + n_c:
            s = _smooth((k - n_a - n_b + 1) / n_c)
            p = np.array([x0 - 2 * x0 * s, 0.0, -depth])
            phase = 'in_slot_floor'
        else:
            p = np.array([-x0, 0.0, -depth])
            phase = 'in_slot_floor'
        T = make_transform(np.eye(3), p)
        return ({'table': np.eye(4), 'slot_block': T_wb, 'peg': T_wb @ T},
                {'contact_phase': phase, 'T_block_peg': T})

    cam = look_at(T_wb[:3, 3] + np.array([0.25, -0.35, 0.42]), T_wb[:3, 3])
    return Scene('peg_in_slot', ('table', 'slot_block', 'peg'), n_a + n_b + n_c + n_d, 30.0,
                 cam, seed, world, static=('table', 'slot_block'))


def _base_motion(rng: np.random.Generator, centre: np.ndarray) -> Callable[[float], np.ndarray]:
    """Smooth world pose of a hand-held base link as a function of time t [s]."""
    w = rng.uniform(0.5, 0.8, 4)
    ph = rng.uniform(0, 2 * np.pi, 4)
    yaw0 = rng.uniform(-np.pi, np.pi)

    def T(t: float) -> np.ndarray:
        p = centre + np.array([0.05 * math.sin(w[0] * t + ph[0]),
                               0.03 * math.sin(w[1] * t + ph[1]),
                               0.02 * math.sin(w[2] * t + ph[2])])
        R = _rz(yaw0 + 0.4 * math.sin(w[3] * t + ph[3])) @ _rx(0.25 * math.sin(w[1] * t))
        return make_transform(R, p)
    return T


def _joint_scene(name: str, seed: int) -> Scene:
    from .make_models import JOINTS  # lazy: keeps ``python -m ...make_models`` warning-free
    rng = np.random.default_rng(seed)
    kind = {'revolute_pair': 'revolute', 'prismatic_pair': 'prismatic',
            'spherical_pair': 'spherical'}[name]
    j = JOINTS[kind]
    base, child = str(j['base']), str(j['child'])
    centre = np.array([0.0, 0.0, 0.16])
    T_base = _base_motion(rng, centre)
    w = rng.uniform(0.8, 1.2, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    fps, n = 30.0, 300

    def world(k: int):
        t = k / fps
        Tb = T_base(t)
        info: dict = {'type': kind, 'base': base, 'child': child}
        if kind == 'revolute':
            axis, point = np.array(j['axis'], float), np.array(j['point'], float)
            q = 1.2 * math.sin(w[0] * t + ph[0])
            T_bc = make_transform(rotation_about_axis(axis, q), point)
            info.update(axis_base=axis, point_base=point, axis_child=axis.copy(),
                        point_child=np.zeros(3), q=q)
        elif kind == 'prismatic':
            axis = np.array(j['axis'], float)
            q = 0.09 * math.sin(w[0] * t + ph[0])
            T_bc = make_transform(np.eye(3), q * axis)
            info.update(axis_base=axis, axis_child=axis.copy(), q=q)
        else:
            rv = np.array([0.5 * math.sin(w[0] * t + ph[0]), 0.5 * math.sin(w[1] * t + ph[1]),
                           1.0 * math.sin(w[2] * t + ph[2])])
            ang = float(np.linalg.norm(rv))
            R = rotation_about_axis(rv / ang, ang) if ang > 0 else np.eye(3)
            cen = np.array(j['center'], float)
            T_bc = make_transform(R, cen)
            info.update(center_base=cen, center_child=np.zeros(3), rotation_vector=rv)
        info['T_base_child'] = T_bc
        return {'table': np.eye(4), base: Tb, child: Tb @ T_bc}, {'joint': info}

    cam = look_at(centre + np.array([0.08, -0.36, 0.30]), centre + [0, 0, -0.02])
    return Scene(name, ('table', base, child), n, fps, cam, seed, world, static=('table',))


def _primitives(seed: int) -> Scene:
    rng = np.random.default_rng(seed)
    layout = {'cube': (-0.20, 0.05, 0.04), 'sphere': (-0.10, -0.08, 0.05),
              'cylinder': (0.0, 0.08, 0.05), 'torus': (0.10, -0.06, 0.02),
              'superquadric': (0.20, 0.05, 0.035)}
    yaw0 = {k: rng.uniform(-np.pi, np.pi) for k in layout}
    speed = {k: rng.uniform(0.2, 0.5) * rng.choice([-1, 1]) for k in layout}
    fps, n = 30.0, 300

    def world(k: int):
        t = k / fps
        poses = {'table': np.eye(4)}
        for name, (x, y, z) in layout.items():
            poses[name] = make_transform(_rz(yaw0[name] + speed[name] * t), [x, y, z])
        return poses, {}

    cam = look_at(np.array([0.0, -0.45, 0.50]), np.array([0.0, 0.0, 0.03]))
    return Scene('primitives', ('table',) + tuple(layout), n, fps, cam, seed, world,
                 static=('table',))


def make_scene(name: str, seed: int = 0) -> Scene:
    """
    Build a scene by name.

    :raises ValueError: for an unknown scene name (the message lists the known ones).
    """
    if name == 'peg_in_hole':
        return _peg_in_hole(int(seed))
    if name == 'peg_in_slot':
        return _peg_in_slot(int(seed))
    if name in ('revolute_pair', 'prismatic_pair', 'spherical_pair'):
        return _joint_scene(name, int(seed))
    if name == 'primitives':
        return _primitives(int(seed))
    raise ValueError(f'unknown scene {name!r}; choose one of: {", ".join(SCENES)}')
