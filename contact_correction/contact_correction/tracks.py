"""
Synthetic assembly tracks with exact contact relations and realistic stereo pose errors.

Used by the benchmark ``bench/contact_tracks.py`` and the tests. Each track is a sequence of
true relative poses of a moving object in a fixed object's model frame (exactly in contact, or
clearly apart), with a phase label per frame; :func:`noisy_track` adds pose errors that are
correlated along the track (a first-order autoregressive process per component, as a tracker
that follows its previous pose makes them) and expresses everything in a camera frame.

Tracks (metres):

* ``t_peg_slot_y``: :func:`~contact_correction.shapes.t_peg_mesh` slid along y into
  :func:`~contact_correction.shapes.t_slot_block_mesh` (tight stem, bar on the shoulders),
  held inserted flush (the peg's large faces coplanar with the block's), pulled back out;
* ``t_peg_pull_up``: slid in along y, held, pulled up out of the open slot (stem walls only);
* ``peg_hole``: the shipped ``peg`` sliding on ``hole_block``'s top across the hole's edge,
  lifted, inserted into the hole (zero clearance), held, pulled out;
* ``peg_slot``: ``peg`` sliding along ``slot_block``'s slot on its floor, then lifted out.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
from stereo_manip_tools.transforms import make_transform, rotation_about_axis

from .contact_relation import evaluate_contacts
from .optimal_correction import constraint_matrix
from .polyhedron import load_polyhedron, Polyhedron
from .shapes import t_peg_mesh, t_slot_block_mesh

__all__ = ['Track', 'track_models', 'make_tracks', 'noisy_track', 'correlated_noise',
           'equivalent_relations']


@dataclass
class Track:
    """
    A true track.

    :ivar name: track name.
    :ivar moving: moving object's polyhedron.
    :ivar fixed: fixed object's polyhedron.
    :ivar T_rel: true poses of the moving object in the fixed frame, (N, 4, 4).
    :ivar phases: phase label per frame (N,).
    """

    name: str
    moving: Polyhedron
    fixed: Polyhedron
    T_rel: np.ndarray
    phases: List[str]


def _tr(x: float, y: float, z: float) -> np.ndarray:
    return make_transform(np.eye(3), [x, y, z])


def track_models() -> Dict[str, Polyhedron]:
    """
    Build the polyhedra of the tracks.

    t_peg, t_slot_block (built) and the shipped peg, hole_block, slot_block.
    """
    out = {'t_peg': load_polyhedron(t_peg_mesh()),
           't_slot_block': load_polyhedron(t_slot_block_mesh())}
    for n in ('peg', 'hole_block', 'slot_block'):
        out[n] = load_polyhedron(n)
    return out


def _seq(phases: List[Tuple[str, np.ndarray, Callable[[float], np.ndarray]]]
         ) -> Tuple[np.ndarray, List[str]]:
    T, lab = [], []
    for name, values, f in phases:
        for v in values:
            T.append(f(float(v)))
            lab.append(name)
    return np.asarray(T), lab


def make_tracks(models: Dict[str, Polyhedron]) -> List[Track]:
    """Make the four true tracks (see the module docstring)."""
    tp, tb = models['t_peg'], models['t_slot_block']
    peg, hole, slot = models['peg'], models['hole_block'], models['slot_block']
    lin = np.linspace
    out = []
    T, lab = _seq([
        ('approach', lin(0.06, 0.026, 6), lambda y: _tr(0, y, 0)),
        ('sliding_in', lin(0.0185, 0.0, 20)[:-1], lambda y: _tr(0, y, 0)),
        ('inserted_flush', np.zeros(15), lambda y: _tr(0, y, 0)),
        ('pulled_out', lin(0.0, 0.0185, 16)[1:], lambda y: _tr(0, y, 0)),
        ('free', lin(0.026, 0.06, 6), lambda y: _tr(0, y, 0)),
    ])
    out.append(Track('t_peg_slot_y', tp, tb, T, lab))
    T, lab = _seq([
        ('sliding_in', lin(0.0185, 0.0, 16)[:-1], lambda y: _tr(0, y, 0)),
        ('inserted_flush', np.zeros(12), lambda y: _tr(0, y, 0)),
        ('pulled_out', lin(0.0, 0.033, 16)[1:], lambda z: _tr(0, 0, z)),
        ('free', lin(0.045, 0.08, 6), lambda z: _tr(0, 0, z)),
    ])
    out.append(Track('t_peg_pull_up', tp, tb, T, lab))
    T, lab = _seq([
        ('sliding_on_top', lin(0.07, 0.008, 22), lambda x: _tr(x, 0.004, 0)),
        ('free', lin(0.012, 0.03, 5), lambda z: _tr(0.0, 0.0, z)),
        ('inserting', lin(-0.004, -0.04, 14), lambda z: _tr(0, 0, z)),
        ('inserted', np.full(10, -0.04), lambda z: _tr(0, 0, z)),
        ('pulled_out', lin(-0.04, -0.004, 12)[1:], lambda z: _tr(0, 0, z)),
        ('free', lin(0.012, 0.04, 5), lambda z: _tr(0, 0, z)),
    ])
    out.append(Track('peg_hole', peg, hole, T, lab))
    T, lab = _seq([
        ('sliding_in_slot', lin(-0.05, 0.05, 26), lambda x: _tr(x, 0, -0.04)),
        ('pulled_out', lin(-0.04, -0.004, 12)[1:], lambda z: _tr(0.05, 0, z)),
        ('free', lin(0.012, 0.04, 5), lambda z: _tr(0.05, 0, z)),
    ])
    out.append(Track('peg_slot', peg, slot, T, lab))
    return out


def correlated_noise(rng: np.random.Generator, n: int, sigma: float, rho: float
                     ) -> np.ndarray:
    """
    Draw AR(1) noise (n, 3).

    AR(1) noise (n, 3), stationary standard deviation ``sigma`` per component and
    frame-to-frame correlation ``rho``.
    """
    e = np.empty((n, 3))
    e[0] = rng.normal(size=3) * sigma
    s = sigma * np.sqrt(1.0 - rho * rho)
    for k in range(1, n):
        e[k] = rho * e[k - 1] + rng.normal(size=3) * s
    return e


def noisy_track(track: Track, rng: np.random.Generator, sigma_t: float, sigma_r: float,
                rho: float = 0.85, pivot: Optional[np.ndarray] = None
                ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """
    Camera-frame poses of a track.

    The fixed object at a (random) pose in front of the camera, the moving object's true pose and
    its observation with correlated errors (translation ``sigma_t`` [m] per axis, rotation
    ``sigma_r`` [rad] per axis about the moving object's origin, or about ``pivot``).

    :param pivot: (3,) the point of the moving object [m, its model frame] the rotation errors
        turn about, where they are independent of the translation errors (a surface-fitting
        localiser's errors turn about the middle of the seen surface); None: the origin.
    :returns: (T_fixed (4, 4), T_moving_true (N, 4, 4), T_moving_observed (N, 4, 4)).
    """
    a = rng.normal(size=3)
    R0 = rotation_about_axis(a, 0.4 + 0.3 * rng.random()) @ rotation_about_axis(
        np.array([1.0, 0.0, 0.0]), -2.2)
    T_fixed = make_transform(R0, [0.02 * rng.normal(), 0.02 * rng.normal(), 0.6])
    n = len(track.T_rel)
    et = correlated_noise(rng, n, sigma_t, rho)
    er = correlated_noise(rng, n, sigma_r, rho)
    true = np.array([T_fixed @ T for T in track.T_rel])
    obs = true.copy()
    for k in range(n):
        ang = float(np.linalg.norm(er[k]))
        Rn = rotation_about_axis(er[k], ang) if ang > 0 else np.eye(3)
        obs[k, :3, :3] = Rn @ true[k, :3, :3]
        obs[k, :3, 3] = true[k, :3, 3] + et[k]
        if pivot is not None:     # the rotation turns about the pivot: it stays in place
            c = true[k, :3, :3] @ np.asarray(pivot, dtype=float)
            obs[k, :3, 3] += c - Rn @ c
    return T_fixed, true, obs


def equivalent_relations(m: Polyhedron, f: Polyhedron, T_true: np.ndarray, truth, pairs) -> bool:
    """
    Check that ``pairs`` holds at the true pose and spans the true relation's constraints.

    How the tests and the benchmark score a recognised relation against a track's truth: every
    pair of ``pairs`` is in contact at ``T_true`` (4x4, moving in fixed frame) and its constraint
    matrix has the rank of the truth's and of both stacked (translation columns scaled by the
    moving object's size). A pair that is not defined at ``T_true`` (an edge-edge pair whose
    edges are parallel there) does not hold: the relation is not equivalent.
    """
    if not truth or not pairs:
        return not truth and not pairs
    try:
        d = evaluate_contacts(m, f, T_true, list(pairs)).distances
    except ValueError:      # e.g. an edge-edge pair with parallel edges at the true pose
        return False
    if np.abs(d).max() > 1e-6:
        return False
    s = np.array([1.0 / m.size] * 3 + [1.0] * 3)
    A1 = constraint_matrix(m, f, T_true, list(truth))[0] * s
    A2 = constraint_matrix(m, f, T_true, list(pairs))[0] * s

    def rank(A):
        sv = np.linalg.svd(A, compute_uv=False)
        return int(np.count_nonzero(sv > 1e-6 * sv[0]))
    return rank(A1) == rank(A2) == rank(np.vstack([A1, A2]))
