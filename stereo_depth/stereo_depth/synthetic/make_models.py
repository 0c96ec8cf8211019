"""
Generator of the object models shipped in ``stereo_manip_models/models/`` (pure numpy).

Run ``python -m stereo_depth.synthetic.make_models [out_dir]`` to (re)write every model; the
committed OBJ files are exactly its output, so the models are reproducible. All models are in
metres, closed 2-manifolds whose faces are simple convex planar polygons listed
counter-clockwise seen from outside (outward right-hand normals).

Frames (each model's own frame; the scenes place them in the left optical frame):

* ``peg``: box 0.04 x 0.04 x 0.12 m, origin at the centre of its bottom face, +z along its length
  (bottom face z = 0, top face z = 0.12).
* ``hole_block``: box 0.16 x 0.16 x 0.08 m with a 0.04 x 0.04 m square through hole at its
  centre (zero clearance for ``peg``), origin at the centre of its top face, +z up (top z = 0,
  bottom z = -0.08). The holed top and bottom faces are split into four convex trapezoids each.
* ``slot_block``: box 0.16 x 0.16 x 0.08 m with a slot 0.04 m wide (|y| <= 0.02) and 0.04 m
  deep (z >= -0.04) cut along x across the whole top; origin at the centre of the top face.
* ``table``: slab 1.0 x 1.0 x 0.02 m, origin at the centre of its top face (top z = 0).
* ``link_base`` / ``link_arm``: revolute pair (LEGO-like bricks). See ``JOINTS``.
* ``slider_base`` / ``slider_carriage``: prismatic pair. See ``JOINTS``.
* ``socket_base`` / ``ball_link``: spherical (ball) pair. See ``JOINTS``.
* primitives ``cube`` (edge 0.08 m, origin at its centre), ``sphere``, ``cylinder``, ``torus``,
  ``superquadric``: the analytic shape and its parameters are written in the OBJ header comment
  and in ``PRIMITIVES`` so exact surface points can be sampled.
"""

from __future__ import annotations

from pathlib import Path
import sys
from typing import Dict, List, Sequence, Tuple

import numpy as np

from stereo_manip_tools.mesh_io import PolygonMesh, save_obj
from stereo_manip_tools.shapes import box_mesh, hole_block_mesh, slot_block_mesh

# the source folder of the data package stereo_manip_models (the committed models)
SOURCE_MODELS_DIR = Path(__file__).resolve().parents[3] / 'stereo_manip_models' / 'models'

__all__ = [
    'box_mesh', 'peg', 'hole_block', 'slot_block', 'table', 'cube', 'sphere', 'cylinder', 'torus',
    'superquadric', 'build_models', 'write_models', 'JOINTS', 'PRIMITIVES', 'MODEL_NAMES',
    'check_closed_manifold',
]

#: Analytic primitive parameters [m]; the meshes are inscribed tessellations of these surfaces.
PRIMITIVES: Dict[str, Dict[str, float]] = {
    'cube': {'edge': 0.08},
    'sphere': {'radius': 0.05, 'n_lat': 24, 'n_lon': 48},
    'cylinder': {'radius': 0.04, 'height': 0.10, 'n_sides': 64},
    'torus': {'major_radius': 0.05, 'minor_radius': 0.02, 'n_major': 48, 'n_minor': 24},
    'superquadric': {'a1': 0.05, 'a2': 0.04, 'a3': 0.035, 'eps1': 0.5, 'eps2': 0.7,
                     'n_eta': 32, 'n_omega': 48},
}

#: Joint definitions of the articulated pairs, in the frame of the first (base) link [m].
#: ``child_origin(q)`` = base-frame pose of the child link at joint coordinate q.
JOINTS: Dict[str, Dict[str, object]] = {
    'revolute': {
        'base': 'link_base', 'child': 'link_arm',
        # link_base: brick 0.128 x 0.032 x 0.0192 (LEGO 2x8), origin at the centre of its top
        # face. link_arm: brick 0.128 x 0.032 x 0.0192 whose origin is at the centre of its
        # bottom face 0.048 m from one end: it rotates about the base z axis through the point
        # (0.048, 0, 0) of the base frame (the stud of the base brick).
        'axis': (0.0, 0.0, 1.0), 'point': (0.048, 0.0, 0.0),
    },
    'prismatic': {
        'base': 'slider_base', 'child': 'slider_carriage',
        # slider_base: rail 0.30 x 0.06 x 0.02, origin at the centre of its top face.
        # slider_carriage: 0.06 x 0.08 x 0.04 box, origin at the centre of its bottom face; it
        # slides along base +x with its origin at (q, 0, 0).
        'axis': (1.0, 0.0, 0.0), 'point': (0.0, 0.0, 0.0),
    },
    'spherical': {
        'base': 'socket_base', 'child': 'ball_link',
        # socket_base: 0.10 x 0.10 x 0.05 block, origin at the centre of its top face = joint
        # centre. ball_link: 0.03 x 0.03 x 0.15 bar spanning z in [0.03, 0.18] of its own frame,
        # whose origin (the ball centre) stays at the base-frame point ``center``.
        'center': (0.0, 0.0, 0.0),
    },
}


def peg() -> PolygonMesh:
    """Peg: 0.04 x 0.04 x 0.12 m box, origin at the bottom-face centre, +z along its length."""
    return box_mesh((-0.02, -0.02, 0.0), (0.02, 0.02, 0.12), 'peg')


def hole_block(size: float = 0.16, height: float = 0.08, hole: float = 0.04) -> PolygonMesh:
    """Block with a square through hole; origin at the top-face centre, +z up."""
    return hole_block_mesh(size, height, hole, 'hole_block')


def slot_block(size: float = 0.16, height: float = 0.08, width: float = 0.04,
               depth: float = 0.04) -> PolygonMesh:
    """Block with a slot along x across the top; origin at the top-face centre, +z up."""
    return slot_block_mesh(size, size, height, width, depth, 'slot_block')


def table(size: float = 1.0, thickness: float = 0.02) -> PolygonMesh:
    """Table slab ``size`` x ``size`` x ``thickness`` m, origin at its top-face centre."""
    s = size / 2
    return box_mesh((-s, -s, -thickness), (s, s, 0.0), 'table')


def cube(edge: float = PRIMITIVES['cube']['edge']) -> PolygonMesh:
    """Cube of edge ``edge`` [m] centred at the origin."""
    e = edge / 2
    return box_mesh((-e, -e, -e), (e, e, e), 'cube')


def _revolution_grid(ring_xy: np.ndarray, ring_z: np.ndarray, profile: np.ndarray,
                     name: str) -> PolygonMesh:
    """
    Surface P(i, j) = (profile[i] * ring_xy[j], ring_z[i]) closed by polar caps.

    ``profile`` (n_i,) radial factor, ``ring_z`` (n_i,) heights from bottom (-z) to top,
    ``ring_xy`` (n_j, 2) CCW around +z. Quads between rings are trapezoids (planar) because
    both ring edges are parallel to ring_xy[j+1] - ring_xy[j]. The first and last rows must
    have profile 0 (poles); they are collapsed to single vertices.
    """
    n_i, n_j = len(profile), len(ring_xy)
    V = [(0.0, 0.0, ring_z[0])]
    for i in range(1, n_i - 1):
        for j in range(n_j):
            V.append((profile[i] * ring_xy[j, 0], profile[i] * ring_xy[j, 1], ring_z[i]))
    V.append((0.0, 0.0, ring_z[-1]))
    top = len(V) - 1

    def idx(i: int, j: int) -> int:
        return 1 + (i - 1) * n_j + (j % n_j)

    F: List[List[int]] = []
    for j in range(n_j):
        F.append([0, idx(1, j + 1), idx(1, j)])  # bottom cap (normal -z side): CCW from outside
    for i in range(1, n_i - 2):
        for j in range(n_j):
            F.append([idx(i, j), idx(i, j + 1), idx(i + 1, j + 1), idx(i + 1, j)])
    for j in range(n_j):
        F.append([top, idx(n_i - 2, j), idx(n_i - 2, j + 1)])
    return PolygonMesh(np.array(V, dtype=float), F, name)


def _ring(n: int, a: float = 1.0, b: float = 1.0, e: float = 1.0) -> np.ndarray:
    w = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(w), np.sin(w)
    return np.stack([a * np.sign(c) * np.abs(c) ** e, b * np.sign(s) * np.abs(s) ** e], axis=1)


def sphere() -> PolygonMesh:
    """UV sphere of radius ``PRIMITIVES['sphere']['radius']`` centred at the origin."""
    p = PRIMITIVES['sphere']
    eta = np.linspace(-np.pi / 2, np.pi / 2, int(p['n_lat']) + 1)
    prof = np.cos(eta)
    prof[0] = prof[-1] = 0.0
    return _revolution_grid(_ring(int(p['n_lon'])), p['radius'] * np.sin(eta),
                            p['radius'] * prof, 'sphere')


def superquadric() -> PolygonMesh:
    """
    Superellipsoid x = a1 C(eta)^e1 C(w)^e2, y = a2 C(eta)^e1 S(w)^e2, z = a3 S(eta)^e1.

    C/S are the signed powers of cos/sin; implicit form
    ``((|x/a1|^(2/e2) + |y/a2|^(2/e2))^(e2/e1) + |z/a3|^(2/e1)) = 1``.
    """
    p = PRIMITIVES['superquadric']
    eta = np.linspace(-np.pi / 2, np.pi / 2, int(p['n_eta']) + 1)
    c, s = np.cos(eta), np.sin(eta)
    prof = np.sign(c) * np.abs(c) ** p['eps1']
    prof[0] = prof[-1] = 0.0
    z = p['a3'] * np.sign(s) * np.abs(s) ** p['eps1']
    return _revolution_grid(_ring(int(p['n_omega']), p['a1'], p['a2'], p['eps2']), z, prof,
                            'superquadric')


def cylinder() -> PolygonMesh:
    """Cylinder of radius r and height h about z, centred at the origin (z in [-h/2, h/2])."""
    p = PRIMITIVES['cylinder']
    n, r, h = int(p['n_sides']), p['radius'], p['height']
    ring = _ring(n) * r
    V = [(x, y, -h / 2) for x, y in ring] + [(x, y, h / 2) for x, y in ring]
    F = [list(range(n - 1, -1, -1)), list(range(n, 2 * n))]
    for j in range(n):
        k = (j + 1) % n
        F.append([j, k, n + k, n + j])
    return PolygonMesh(np.array(V, dtype=float), F, 'cylinder')


def torus() -> PolygonMesh:
    """Torus about z: ((R + r cos v) cos u, (R + r cos v) sin u, r sin v), centred at origin."""
    p = PRIMITIVES['torus']
    nu, nv, R, r = int(p['n_major']), int(p['n_minor']), p['major_radius'], p['minor_radius']
    u = np.linspace(0, 2 * np.pi, nu, endpoint=False)
    v = np.linspace(0, 2 * np.pi, nv, endpoint=False)
    V = []
    for i in range(nu):
        for j in range(nv):
            rho = R + r * np.cos(v[j])
            V.append((rho * np.cos(u[i]), rho * np.sin(u[i]), r * np.sin(v[j])))
    F = []
    for i in range(nu):
        for j in range(nv):
            i1, j1 = (i + 1) % nu, (j + 1) % nv
            F.append([i * nv + j, i1 * nv + j, i1 * nv + j1, i * nv + j1])
    return PolygonMesh(np.array(V, dtype=float), F, 'torus')


def _joint_models() -> List[Tuple[PolygonMesh, str]]:
    out = []
    out.append((box_mesh((-0.064, -0.016, -0.0192), (0.064, 0.016, 0.0), 'link_base'),
                'LEGO-like 2x8 brick 0.128 x 0.032 x 0.0192 m, origin at top-face centre.\n'
                'Revolute joint with link_arm: axis +z through (0.048, 0, 0) of this frame.'))
    out.append((box_mesh((-0.016, -0.016, 0.0), (0.112, 0.016, 0.0192), 'link_arm'),
                'LEGO-like 2x8 brick 0.128 x 0.032 x 0.0192 m; origin on the joint axis at the\n'
                'bottom face, 0.016 m from one end; rotates about its own +z axis.'))
    out.append((box_mesh((-0.15, -0.03, -0.02), (0.15, 0.03, 0.0), 'slider_base'),
                'Rail 0.30 x 0.06 x 0.02 m, origin at top-face centre; prismatic axis +x.'))
    out.append((box_mesh((-0.03, -0.04, 0.0), (0.03, 0.04, 0.04), 'slider_carriage'),
                'Carriage 0.06 x 0.08 x 0.04 m, origin at bottom-face centre; slides along +x\n'
                'of slider_base with its origin at (q, 0, 0) of the base frame.'))
    out.append((box_mesh((-0.05, -0.05, -0.05), (0.05, 0.05, 0.0), 'socket_base'),
                'Block 0.10 x 0.10 x 0.05 m, origin at top-face centre = spherical joint centre.'))
    out.append((box_mesh((-0.015, -0.015, 0.03), (0.015, 0.015, 0.18), 'ball_link'),
                'Bar 0.03 x 0.03 x 0.15 m spanning z in [0.03, 0.18]; origin = ball centre\n'
                '(spherical joint), which stays at the origin of socket_base.'))
    return out


def build_models() -> Dict[str, Tuple[PolygonMesh, str]]:
    """All shipped models: name -> (mesh, header comment)."""
    sp, cy, to, sq = (PRIMITIVES[k] for k in ('sphere', 'cylinder', 'torus', 'superquadric'))
    models = {
        'peg': (peg(), 'Box 0.04 x 0.04 x 0.12 m; origin at bottom-face centre, +z along length.'),
        'hole_block': (hole_block(),
                       'Box 0.16 x 0.16 x 0.08 m with a 0.04 x 0.04 m square through hole\n'
                       '(zero clearance for peg); origin at top-face centre, +z up.'),
        'slot_block': (slot_block(),
                       'Box 0.16 x 0.16 x 0.08 m with a slot |y| <= 0.02, z >= -0.04 along x\n'
                       'across the top; origin at top-face centre, +z up.'),
        'table': (table(), 'Slab 1.0 x 1.0 x 0.02 m; origin at top-face centre, +z up.'),
        'cube': (cube(), 'Cube, edge 0.08 m, centred at the origin. Exact shape.'),
        'sphere': (sphere(),
                   f'Inscribed UV tessellation of the sphere x^2 + y^2 + z^2 = r^2, '
                   f'r = {sp["radius"]} m,\ncentred at the origin '
                   f'({int(sp["n_lat"])} latitude x {int(sp["n_lon"])} longitude bands).'),
        'cylinder': (cylinder(),
                     f'Inscribed {int(cy["n_sides"])}-gon prism of the cylinder x^2 + y^2 = r^2, '
                     f'|z| <= h/2,\nr = {cy["radius"]} m, h = {cy["height"]} m, centred at the '
                     'origin, axis z.'),
        'torus': (torus(),
                  'Torus (sqrt(x^2 + y^2) - R)^2 + z^2 = r^2 about z, centred at the origin,\n'
                  f'R = {to["major_radius"]} m, r = {to["minor_radius"]} m; vertices on the '
                  f'surface, {int(to["n_major"])} x {int(to["n_minor"])} quads.'),
        'superquadric': (superquadric(),
                         'Superellipsoid ((|x/a1|^(2/e2) + |y/a2|^(2/e2))^(e2/e1) + '
                         '|z/a3|^(2/e1)) = 1,\n'
                         f'a1 = {sq["a1"]} m, a2 = {sq["a2"]} m, a3 = {sq["a3"]} m, '
                         f'e1 = {sq["eps1"]}, e2 = {sq["eps2"]}, centred at the origin;\n'
                         'parametric x = a1 C(eta)^e1 C(w)^e2, y = a2 C(eta)^e1 S(w)^e2, '
                         'z = a3 S(eta)^e1 (signed powers);\n'
                         f'vertices on the surface, {int(sq["n_eta"])} eta x '
                         f'{int(sq["n_omega"])} omega bands.'),
    }
    for mesh, comment in _joint_models():
        models[mesh.name] = (mesh, comment)
    return models


MODEL_NAMES: Tuple[str, ...] = (
    'peg', 'hole_block', 'slot_block', 'table', 'cube', 'sphere', 'cylinder', 'torus',
    'superquadric', 'link_base', 'link_arm', 'slider_base', 'slider_carriage', 'socket_base',
    'ball_link',
)


def check_closed_manifold(mesh: PolygonMesh, planarity_tol: float = 1e-9) -> None:
    """
    Raise ``ValueError`` unless the mesh is a closed, oriented, convex-faced solid.

    Raise ``ValueError`` unless every edge is used once in each direction (closed, oriented
    2-manifold), every face is planar and strictly convex-or-flat, and the volume is positive.
    """
    from collections import Counter
    directed = Counter()
    for f in mesh.faces:
        for a, b in zip(f, np.roll(f, -1)):
            directed[(int(a), int(b))] += 1
    for (a, b), c in directed.items():
        if c != 1 or directed.get((b, a), 0) != 1:
            raise ValueError(f'{mesh.name}: edge {a}-{b} is not shared by exactly two faces '
                             'with opposite orientation')
    normals = mesh.face_normals()
    for i, f in enumerate(mesh.faces):
        P = mesh.vertices[f]
        d = (P - P[0]) @ normals[i]
        if np.max(np.abs(d)) > planarity_tol:
            raise ValueError(f'{mesh.name}: face {i} not planar ({np.max(np.abs(d)):.2e} m)')
        e = np.roll(P, -1, axis=0) - P
        cr = np.cross(e, np.roll(e, -1, axis=0)) @ normals[i]
        if np.any(cr < -1e-15):
            raise ValueError(f'{mesh.name}: face {i} is not convex')
    T = mesh.triangles()
    V = mesh.vertices
    vol = np.einsum('ij,ij->i', V[T[:, 0]], np.cross(V[T[:, 1]], V[T[:, 2]])).sum() / 6
    if vol <= 0:
        raise ValueError(f'{mesh.name}: non-positive volume {vol}: faces wound inwards')


def write_models(out_dir: Path) -> List[Path]:
    """Write every model as ``<out_dir>/<name>.obj`` after checking it; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, (mesh, comment) in build_models().items():
        check_closed_manifold(mesh)
        path = out_dir / f'{name}.obj'
        save_obj(mesh, path,
                 comment=comment + '\nGenerated by stereo_depth.synthetic.make_models.')
        paths.append(path)
    return paths


def main(argv: Sequence[str] | None = None) -> None:
    """Command line: ``make_models [out_dir]`` (default: ``stereo_manip_models/models/``)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    out = Path(argv[0]) if argv else SOURCE_MODELS_DIR
    for p in write_models(out):
        print(p)


if __name__ == '__main__':
    main()
