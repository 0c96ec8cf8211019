"""
Polygon mesh I/O: the one loader every package uses for object models (pure numpy).

Object models ship as Wavefront OBJ files in metres with polygon faces preserved (a box has six
quadrilateral faces, not twelve triangles), installed by the data package
``stereo_manip_models`` under ``share/stereo_manip_models/models/``. Faces are counter-clockwise
seen from outside, so the right-hand normal points outward.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import os
from pathlib import Path
from typing import List, Optional, Sequence

import numpy as np

from stereo_manip_tools.files import open_regular_file

__all__ = ['PolygonMesh', 'load_obj', 'save_obj', 'find_model', 'surface_centroid',
           'MODEL_PACKAGE']

MODEL_PACKAGE = 'stereo_manip_models'


@dataclass
class PolygonMesh:
    """
    A polygon mesh.

    :ivar vertices: vertex positions [m], shape (N, 3), float64.
    :ivar faces: one int array of vertex indices per face, counter-clockwise from outside.
    :ivar name: model name (file stem).
    """

    vertices: np.ndarray
    faces: List[np.ndarray] = field(default_factory=list)
    name: str = ''

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=float).reshape(-1, 3)
        self.faces = [np.asarray(f, dtype=np.int64).reshape(-1) for f in self.faces]
        n = len(self.vertices)
        for i, f in enumerate(self.faces):
            if len(f) < 3:
                raise ValueError(f'mesh {self.name!r}: face {i} has {len(f)} vertices (< 3)')
            if f.min() < 0 or f.max() >= n:
                raise ValueError(f'mesh {self.name!r}: face {i} indexes a missing vertex')

    def triangles(self) -> np.ndarray:
        """Fan-triangulate every (convex) polygon face; int array of shape (M, 3)."""
        tris = [[f[0], f[k], f[k + 1]] for f in self.faces for k in range(1, len(f) - 1)]
        return np.asarray(tris, dtype=np.int64).reshape(-1, 3)

    def face_normals(self) -> np.ndarray:
        """Compute the unit outward normal of each face (Newell's method), shape (F, 3)."""
        normals = np.zeros((len(self.faces), 3))
        for i, f in enumerate(self.faces):
            p = self.vertices[f]
            q = np.roll(p, -1, axis=0)
            n = np.array([
                np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
                np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
                np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1])),
            ])
            norm = np.linalg.norm(n)
            normals[i] = n / norm if norm > 0 else n
        return normals

    def transformed(self, T: np.ndarray) -> 'PolygonMesh':
        """Copy of the mesh with vertices mapped by the 4x4 transform ``T``."""
        V = self.vertices @ np.asarray(T)[:3, :3].T + np.asarray(T)[:3, 3]
        return PolygonMesh(V, [f.copy() for f in self.faces], self.name)


def surface_centroid(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """
    Return the area-weighted centroid (3,) [m] of a triangle mesh's surface.

    :param vertices: (V, 3) [m]; :param triangles: (T, 3) vertex indices.
    :raises ValueError: the triangles have no area.
    """
    V = np.asarray(vertices, float)
    tri = V[np.asarray(triangles, dtype=np.int64).reshape(-1, 3)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    if not area.sum() > 0:
        raise ValueError('surface_centroid: the triangles have no area')
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum()


def load_obj(path: os.PathLike | str) -> PolygonMesh:
    """
    Read a Wavefront OBJ file (``v`` and ``f`` records; ``f a/b/c`` forms accepted).

    Negative (relative) indices are resolved; texture and normal records are ignored.

    :raises FileNotFoundError: if ``path`` does not exist.
    :raises ValueError: on a malformed record, naming the file and line, or a path that is not
        a regular file (:class:`stereo_manip_tools.files.NotARegularFileError`: a FIFO would
        block).
    """
    path = Path(path)
    vertices: List[List[float]] = []
    faces: List[List[int]] = []
    with open_regular_file(path, 'OBJ model') as fh:
        for lineno, line in enumerate(fh, 1):
            parts = line.split()
            if not parts or parts[0].startswith('#'):
                continue
            try:
                if parts[0] == 'v':
                    vertices.append([float(x) for x in parts[1:4]])
                elif parts[0] == 'f':
                    idx = []
                    for tok in parts[1:]:
                        i = int(tok.split('/')[0])
                        idx.append(i - 1 if i > 0 else len(vertices) + i)
                    faces.append(idx)
            except ValueError as exc:
                raise ValueError(f'{path}:{lineno}: malformed OBJ record '
                                 f'{line.strip()!r}') from exc
    if not vertices:
        raise ValueError(f'{path}: no vertices found; is it an OBJ file?')
    return PolygonMesh(np.array(vertices), faces, path.stem)


def save_obj(mesh: PolygonMesh, path: os.PathLike | str, comment: str = '') -> None:
    """Write a mesh as OBJ with polygon faces (1-based indices), units metres."""
    with open(path, 'w', encoding='utf-8') as fh:
        name = mesh.name or Path(path).stem
        fh.write(f'# {name}: units metres, polygon faces CCW from outside\n')
        for line in comment.splitlines():
            fh.write(f'# {line}\n')
        for v in mesh.vertices:
            fh.write(f'v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}\n')
        for f in mesh.faces:
            fh.write('f ' + ' '.join(str(int(i) + 1) for i in f) + '\n')


def _model_dirs() -> Sequence[Path]:
    dirs = []
    env = os.environ.get('STEREO_MANIP_MODEL_PATH')
    if env:
        dirs.extend(Path(p) for p in env.split(os.pathsep) if p)
    try:
        from ament_index_python.packages import get_package_share_directory
        dirs.append(Path(get_package_share_directory(MODEL_PACKAGE)) / 'models')
    except Exception:  # noqa: BLE001 - ament index absent or package not built: use source tree
        pass
    dirs.append(Path(__file__).resolve().parents[2] / MODEL_PACKAGE / 'models')
    return dirs


def find_model(name: str, directories: Optional[Sequence[Path]] = None) -> Path:
    """
    Path of the shipped model ``<name>.obj``.

    Looks in ``$STEREO_MANIP_MODEL_PATH``, then ``share/stereo_manip_models/models`` of the
    installed package, then the source tree.

    :raises FileNotFoundError: naming the directories searched.
    """
    dirs = list(directories) if directories is not None else list(_model_dirs())
    fname = name if name.endswith('.obj') else name + '.obj'
    for d in dirs:
        p = Path(d) / fname
        if p.is_file():
            return p
    raise FileNotFoundError(f'model {name!r} not found in: ' + ', '.join(str(d) for d in dirs))
