"""
``fit_ip``: fit an implicit polynomial to a point file; write coefficients and a figure.

Usage::

    ros2 run ip_modeler fit_ip points.xyz [--normals-from-file] [--max-degree 8]
        [--target-rms 0.0005] [--output out/cube]
    ros2 run ip_modeler fit_ip --shape cube --noise 0.005    # synthetic demo data

Input formats: ``.npy`` (N x 3 or N x 6 array: x y z [nx ny nz]), text ``.xyz/.txt/.csv``
(the same columns, whitespace or comma separated, ``#`` comments), ``.ply/.pcd`` (read with
open3d, normals used when present). Coordinates in metres.

Writes ``<output>.json`` (degree, graded_lex coefficients, normalisation centre/scale, true RMS
and max distance, per-degree history) and ``<output>.png``: the data beside the zero set of the
model, like the chapter's Fig. 15 (matplotlib, Agg backend).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
import sys
from typing import List, Optional, Tuple

from ip_modeler.evaluation import bounding_region, distance_to_zero_set, zero_set_mesh
from ip_modeler.fitting import (DEFAULT_3L_OFFSET, estimate_normals, fit_implicit_polynomial,
                                FitResult, MAX_SUPPORTED_DEGREE)
from ip_modeler.incremental_qr import STABILIZATION_MODES
from ip_modeler.monomials import monomial_exponents, MONOMIAL_ORDER
from ip_modeler.shapes import add_noise, sample_shape, SHAPES, visible_half
import numpy as np

__all__ = ['load_points', 'write_results', 'plot_fit', 'main']


def load_points(path: Path) -> Tuple[np.ndarray, Optional[np.ndarray]]:
    """
    Points (N, 3) [m] and normals (N, 3) or None from a point file.

    :raises ValueError: unknown format or wrong column count, naming the file.
    :raises FileNotFoundError: missing file.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f'{path}: no such file')
    suffix = path.suffix.lower()
    if suffix in ('.ply', '.pcd'):
        import open3d as o3d

        pc = o3d.io.read_point_cloud(str(path))
        P = np.asarray(pc.points, dtype=float)
        N = np.asarray(pc.normals, dtype=float) if pc.has_normals() else None
        if len(P) == 0:
            raise ValueError(f'{path}: no points read')
        return P, N
    if suffix == '.npy':
        A = np.load(path)
    elif suffix in ('.xyz', '.txt', '.csv'):
        text = path.read_text().replace(',', ' ')
        rows = [line.split() for line in text.splitlines()
                if line.strip() and not line.lstrip().startswith('#')]
        try:
            A = np.array([[float(v) for v in r] for r in rows])
        except ValueError as exc:
            raise ValueError(f'{path}: not a numeric table ({exc})') from None
    else:
        raise ValueError(f'{path}: unknown point format {suffix!r} '
                         '(use .npy, .xyz, .txt, .csv, .ply or .pcd)')
    A = np.asarray(A, dtype=float)
    if A.ndim != 2 or A.shape[1] not in (3, 6):
        raise ValueError(f'{path}: expected N x 3 (x y z) or N x 6 (x y z nx ny nz) values, '
                         f'got shape {A.shape}')
    return A[:, :3], (A[:, 3:6] if A.shape[1] == 6 else None)


def write_results(path: Path, result: FitResult, rms: float, max_d: float,
                  n_points: int) -> None:
    """JSON file of the fitted model and its history."""
    m = result.model
    data = {
        'degree': m.degree,
        'monomial_order': MONOMIAL_ORDER,
        'exponents': monomial_exponents(m.degree).tolist(),
        'coefficients': m.coefficients.tolist(),
        'centre_m': m.centre.tolist(),
        'scale_m': m.scale,
        'note': 'f(x) = sum a_ijk u^i v^j w^k with (u, v, w) = (x - centre) / scale',
        'rms_distance_m': rms,
        'max_distance_m': max_d,
        'point_count': n_points,
        'method': m.method,
        'status': m.status,
        'history': [vars(s) for s in result.steps],
        'seconds': result.seconds,
    }
    path.write_text(json.dumps(data, indent=2) + '\n')


def plot_fit(path: Path, points: np.ndarray, mesh: Tuple[np.ndarray, np.ndarray],
             title: str) -> None:
    """Figure like Fig. 15: the data (left) beside the IP zero set (right)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    fig = plt.figure(figsize=(10, 5))
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.6 * float(np.max(hi - lo))
    for i, label in enumerate(('original data', 'IP model')):
        ax = fig.add_subplot(1, 2, i + 1, projection='3d')
        if i == 0:
            ax.scatter(points[:, 0], points[:, 1], points[:, 2], s=1, c=points[:, 2],
                       cmap='viridis')
        elif len(mesh[1]):
            V, T = mesh
            poly = Poly3DCollection(V[T], alpha=0.9, linewidths=0)
            normals = np.cross(V[T[:, 1]] - V[T[:, 0]], V[T[:, 2]] - V[T[:, 0]])
            normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
            shade = 0.35 + 0.65 * np.abs(normals @ np.array([0.3, -0.4, 0.87]))
            poly.set_facecolor(plt.cm.Blues(0.3 + 0.6 * shade))
            ax.add_collection3d(poly)
        for setter, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre):
            setter(c - half, c + half)
        ax.set_box_aspect((1, 1, 1))
        ax.set_title(label)
        ax.set_xlabel('x [m]')
        ax.set_ylabel('y [m]')
        ax.set_zlabel('z [m]')
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _parse(argv: Optional[List[str]]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='fit_ip', description=__doc__.strip().splitlines()[0])
    p.add_argument('input', nargs='?', type=Path, help='point file (.npy/.xyz/.txt/.csv/.ply)')
    p.add_argument('--shape', choices=sorted(SHAPES), help='fit synthetic data instead')
    p.add_argument('--size', type=float, default=0.08, help='synthetic shape size [m]')
    p.add_argument('--noise', type=float, default=0.0, help='synthetic noise sigma [m]')
    p.add_argument('--half', action='store_true', help='synthetic: only the half facing a '
                   'viewer')
    p.add_argument('--points', type=int, default=2000, help='synthetic: number of points')
    p.add_argument('--max-degree', type=int, default=8)
    p.add_argument('--target-rms', type=float, default=0.0,
                   help='stop at the first degree with this RMS first-order distance [m] '
                   '(default: 1 %% of the bounding-box diagonal)')
    p.add_argument('--offset', type=float, default=DEFAULT_3L_OFFSET,
                   help='3L offset (fraction of scale)')
    p.add_argument('--stabilization', choices=STABILIZATION_MODES, default='drop')
    p.add_argument('--ridge', type=float, default=1e-6)
    p.add_argument('--viewpoint', type=float, nargs=3, default=None,
                   help='sensor position [m] for orienting estimated normals')
    p.add_argument('--ignore-file-normals', action='store_true',
                   help='estimate normals even if the file has them')
    p.add_argument('--resolution', type=int, default=64, help='marching-cubes resolution')
    p.add_argument('--output', type=Path, default=None,
                   help='output prefix (default: input name, or ip_<shape>)')
    args = p.parse_args(argv)
    if (args.input is None) == (args.shape is None):
        p.error('give either a point file or --shape')
    if not 1 <= args.max_degree <= MAX_SUPPORTED_DEGREE:
        p.error(f'--max-degree must be in [1, {MAX_SUPPORTED_DEGREE}]')
    return args


def main(argv: Optional[List[str]] = None) -> int:
    args = _parse(argv)
    try:
        if args.shape:
            rng = np.random.default_rng(0)
            n = args.points * (2 if args.half else 1)
            P, N = sample_shape(args.shape, n, args.size, rng)
            if args.half:
                P, N = visible_half(P, N)
            if args.noise > 0:
                P = add_noise(P, args.noise, rng)
                N = None
            name = f'ip_{args.shape}'
        else:
            P, N = load_points(args.input)
            if args.ignore_file_normals:
                N = None
            name = str(args.input.with_suffix(''))
        finite = np.all(np.isfinite(P), axis=1)
        if N is not None:
            finite &= np.all(np.isfinite(N), axis=1)
        if not finite.all():
            print(f'fit_ip: dropping {int((~finite).sum())} rows with NaN/inf values',
                  file=sys.stderr)
            P = P[finite]
            N = N[finite] if N is not None else None
        if N is None:
            view = None if args.viewpoint is None else np.asarray(args.viewpoint)
            if args.shape and args.half:
                view = np.array([0.3, -0.4, 0.866]) * 10 * args.size
            N = estimate_normals(P, viewpoint=view)
        target = args.target_rms or 0.01 * float(np.linalg.norm(P.max(0) - P.min(0)))
        result = fit_implicit_polynomial(P, N, max_degree=args.max_degree, target_rms=target,
                                         offset=args.offset, stabilization=args.stabilization,
                                         ridge=args.ridge)
    except (ValueError, FileNotFoundError) as exc:
        print(f'fit_ip: error: {exc}', file=sys.stderr)
        return 2
    model = result.model
    mesh = zero_set_mesh(model, *bounding_region(P, 0.1), resolution=args.resolution)
    d = distance_to_zero_set(model, P, mesh=mesh)
    rms, max_d = float(np.sqrt(np.mean(d ** 2))), float(np.max(d))
    prefix = Path(args.output) if args.output else Path(name)
    prefix.parent.mkdir(parents=True, exist_ok=True)
    json_path, png_path = Path(f'{prefix}.json'), Path(f'{prefix}.png')
    write_results(json_path, result, rms, max_d, len(P))
    plot_fit(png_path, P, mesh, f'degree {model.degree}: RMS distance {rms * 1e3:.2f} mm, '
             f'max {max_d * 1e3:.2f} mm ({len(P)} points)')
    print(f'fit_ip: degree {model.degree} ({result.stop_reason}); RMS distance '
          f'{rms:.6g} m, max {max_d:.6g} m; wrote {json_path} and {png_path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
