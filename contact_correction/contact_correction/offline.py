"""``correct_trajectory``: offline contact-based correction of a recorded trajectory.

Input, either
  - a CSV file with this header (one row per frame; ``#`` lines are comments; poses in a common
    frame, metres, unit quaternions in ROS order x, y, z, w)::

        stamp_ns,x,y,z,qx,qy,qz,qw[,fixed_x,fixed_y,fixed_z,fixed_qx,fixed_qy,fixed_qz,fixed_qw]

    ``x..qw`` is the observed pose of the moving object; the optional ``fixed_*`` columns give
    the fixed object's pose per frame (otherwise ``--fixed-pose``, default identity); or
  - a rosbag2 bag with the moving object's poses on ``--moving-topic``
    (geometry_msgs/PoseStamped, or nav_msgs/Path whose last message is used) and optionally the
    fixed object's on ``--fixed-topic`` (the newest one before each moving pose is used).

Output: a CSV (``--output``) with header::

    stamp_ns,x,y,z,qx,qy,qz,qw,corrected,method,rotation_rank,constraint_rank,pairs,
    penetration_observed_m,max_residual_m,dx,dy,dz,status

(corrected pose; ``dx, dy, dz`` = change of the moving origin in the fixed object's frame [m]),
and with ``--figure`` a PNG like the chapter's Fig. 9: the observed trajectory and its
corrections by the non-linear step only and by non-linear + optimal, projected onto the
constrained and free translation directions, and onto the plane of the first two fixed-frame
axes.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path
import sys
from typing import List, Optional, Sequence, Tuple

import numpy as np

from stereo_manip_tools.transforms import (
    make_transform, matrix_from_quaternion, quaternion_from_matrix)

from .correction import CorrectionResult
from .polyhedron import load_polyhedron
from .trajectory import correct_trajectory

__all__ = ['read_csv', 'write_csv', 'read_bag_poses', 'plot_fig9', 'main']

POSE_COLUMNS = ['x', 'y', 'z', 'qx', 'qy', 'qz', 'qw']
FIXED_COLUMNS = ['fixed_' + c for c in POSE_COLUMNS]
OUTPUT_COLUMNS = ['stamp_ns', *POSE_COLUMNS, 'corrected', 'method', 'rotation_rank',
                  'constraint_rank', 'pairs', 'penetration_observed_m', 'max_residual_m',
                  'dx', 'dy', 'dz', 'status']


def _pose(values: Sequence[float]) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    return make_transform(matrix_from_quaternion(v[3:7]), v[:3])


def _row(T: np.ndarray) -> List[float]:
    return [*T[:3, 3].tolist(), *quaternion_from_matrix(T[:3, :3]).tolist()]


def read_csv(path: Path) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """Read a trajectory CSV (see module docstring).

    :returns: stamps [ns] (N,), moving poses (N, 4, 4), fixed poses (N, 4, 4) or None.
    :raises ValueError: missing columns or a malformed row, naming the line.
    """
    with open(path, newline='', encoding='utf-8') as fh:
        lines = [ln for ln in fh if ln.strip() and not ln.lstrip().startswith('#')]
    reader = csv.DictReader(lines)
    cols = reader.fieldnames or []
    missing = [c for c in ['stamp_ns', *POSE_COLUMNS] if c not in cols]
    if missing:
        raise ValueError(f'{path}: missing column(s) {", ".join(missing)}; expected header '
                         'stamp_ns,x,y,z,qx,qy,qz,qw[,fixed_x,...,fixed_qw]')
    has_fixed = all(c in cols for c in FIXED_COLUMNS)
    stamps, moving, fixed = [], [], []
    for k, row in enumerate(reader, start=2):
        try:
            stamps.append(int(float(row['stamp_ns'])))
            moving.append([float(row[c]) for c in POSE_COLUMNS])
            if has_fixed:
                fixed.append(_pose([float(row[c]) for c in FIXED_COLUMNS]))
        except (TypeError, ValueError) as exc:
            raise ValueError(f'{path}: data line {k}: {exc}') from exc
    # moving poses are converted without raising: bad ones are reported per frame
    Tm = np.full((len(moving), 4, 4), np.nan)
    for k, v in enumerate(moving):
        try:
            Tm[k] = _pose(v)
        except ValueError:
            pass
    return (np.asarray(stamps, dtype=np.int64), Tm,
            np.asarray(fixed).reshape(-1, 4, 4) if has_fixed else None)


def read_bag_poses(path: Path, moving_topic: str, fixed_topic: Optional[str]
                   ) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """Moving poses (and fixed poses, newest before each moving one) from a rosbag2 bag."""
    from rclpy.serialization import deserialize_message

    from stereo_manip_tools.bag_io import get_message_class, read_bag
    from stereo_manip_tools.conversions import path_to_matrices, pose_stamped_to_matrix

    topics = [moving_topic] + ([fixed_topic] if fixed_topic else [])
    stamps: List[int] = []
    moving: List[np.ndarray] = []
    fixed: List[np.ndarray] = []
    last_fixed: Optional[np.ndarray] = None
    last_path = None
    for m in read_bag(path, topics):
        msg = deserialize_message(m.data, get_message_class(m.msgtype))
        if m.topic == fixed_topic:
            try:
                last_fixed = pose_stamped_to_matrix(msg)[0]
            except ValueError as exc:
                print(f'warning: fixed pose at {m.timestamp} ns ignored: {exc}', file=sys.stderr)
            continue
        if m.msgtype == 'nav_msgs/msg/Path':
            last_path = msg
            continue
        if m.msgtype != 'geometry_msgs/msg/PoseStamped':
            raise ValueError(f'{moving_topic}: type {m.msgtype} is not PoseStamped or Path')
        try:
            T, stamp, _ = pose_stamped_to_matrix(msg)
        except ValueError:
            T, stamp = np.full((4, 4), np.nan), m.timestamp
        stamps.append(stamp)
        moving.append(T)
        fixed.append(last_fixed if last_fixed is not None else np.full((4, 4), np.nan))
    if last_path is not None and not moving:
        Ts, st = path_to_matrices(last_path)
        return st, Ts, None
    if fixed_topic and any(np.isnan(F).any() for F in fixed):
        n = sum(np.isnan(F).any() for F in fixed)
        print(f'warning: {n} moving poses precede the first fixed pose; they are passed '
              'through', file=sys.stderr)
    return (np.asarray(stamps, dtype=np.int64), np.asarray(moving).reshape(-1, 4, 4),
            np.asarray(fixed).reshape(-1, 4, 4) if fixed_topic else None)


def write_csv(path: Path, stamps: np.ndarray, results: Sequence[CorrectionResult]) -> None:
    """Write the corrected trajectory (header ``OUTPUT_COLUMNS``)."""
    with open(path, 'w', newline='', encoding='utf-8') as fh:
        fh.write('# corrected trajectory (contact_correction); poses in the input frame, metres, '
                 'quaternion x y z w; dx dy dz: change in the fixed object frame [m]\n')
        w = csv.writer(fh)
        w.writerow(OUTPUT_COLUMNS)
        for s, r in zip(stamps, results):
            T = np.asarray(r.T_moving, dtype=float).reshape(4, 4)
            pose = _row(T) if np.all(np.isfinite(T)) else [float('nan')] * 7
            w.writerow([int(s), *[f'{v:.9g}' for v in pose], int(r.corrected), r.method,
                        r.rotation_rank, r.constraint_rank, len(r.pairs),
                        f'{r.penetration_before:.6g}', f'{r.max_residual:.6g}',
                        *[f'{v:.9g}' for v in r.translation_change], r.status])


def plot_fig9(path: Path, stamps: np.ndarray, observed: np.ndarray, fixed: np.ndarray,
              nonlinear: Sequence[CorrectionResult], optimal: Sequence[CorrectionResult]
              ) -> None:
    """Fig. 9-like figure: trajectories before / after both corrections."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    def origin_in_fixed(Ts: Sequence[np.ndarray]) -> np.ndarray:
        return np.array([np.linalg.solve(F, T)[:3, 3] if np.all(np.isfinite(T)) else
                         np.full(3, np.nan) for F, T in zip(fixed, Ts)])

    obs = origin_in_fixed(observed)
    nl = origin_in_fixed([r.T_moving for r in nonlinear])
    op = origin_in_fixed([r.T_moving for r in optimal])
    # axes: constrained / free translation directions of the corrected frame with the most
    # free directions (the latest such frame), e.g. sliding along the hole during insertion
    axes, labels = np.eye(3), ['x', 'y', 'z']
    cands = [r for r in optimal if r.corrected and r.directions is not None]
    if cands:
        d = max(reversed(cands), key=lambda r: len(r.directions.free_translation)).directions
        axes = np.vstack([d.constrained_translation, d.free_translation])
        labels = ([f'constrained {i + 1}' for i in range(len(d.constrained_translation))]
                  + [f'free {i + 1}' for i in range(len(d.free_translation))])
    t = (stamps - stamps[0]) * 1e-9 if len(stamps) else stamps
    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    free_k = [k for k, lab in enumerate(labels) if lab.startswith('free')]
    con_k = [k for k, lab in enumerate(labels) if lab.startswith('constrained')]
    panels = [(ax[0, 0], con_k[:1] or [0], 'constrained direction'),
              (ax[0, 1], free_k[:1] or [2], 'free direction')]
    for a, ks, title in panels:
        k = ks[0]
        a.plot(t, obs @ axes[k] * 1e3, 'k.', ms=3, label='observed')
        a.plot(t, nl @ axes[k] * 1e3, 'r-', lw=2, alpha=0.6, label='non-linear only')
        a.plot(t, op @ axes[k] * 1e3, 'b--', lw=1, label='non-linear + optimal')
        a.set_title(f'{title}: {labels[k]} {np.round(axes[k], 3).tolist()}')
        a.set_xlabel('time [s]')
        a.set_ylabel('position [mm]')
        a.legend(fontsize=8)
    a = ax[1, 0]
    a.plot(obs[:, 0] * 1e3, obs[:, 1] * 1e3, 'k.', ms=3, label='observed')
    a.plot(op[:, 0] * 1e3, op[:, 1] * 1e3, 'b-', lw=1, label='non-linear + optimal')
    a.set_xlabel('x (fixed frame) [mm]')
    a.set_ylabel('y (fixed frame) [mm]')
    a.set_aspect('equal', adjustable='datalim')
    a.set_title('trajectory projected on the xy-plane')
    a.legend(fontsize=8)
    a = ax[1, 1]
    for k in free_k or [2]:
        a.plot(t, (nl - obs) @ axes[k] * 1e3, 'r-', lw=2, alpha=0.6,
               label=f'non-linear, {labels[k]}')
        a.plot(t, (op - obs) @ axes[k] * 1e3, 'b--', lw=1, label=f'optimal, {labels[k]}')
    a.set_title('correction along the free direction(s) of the frames in contact')
    a.set_xlabel('time [s]')
    a.set_ylabel('change [mm]')
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog='correct_trajectory',
        description='Correct a recorded moving-object trajectory with contact relations '
                    '(chapter Section 3) and write the corrected CSV (+ a Fig. 9-like plot).')
    ap.add_argument('input', type=Path, help='trajectory CSV or rosbag2 bag directory')
    ap.add_argument('-o', '--output', type=Path, required=True, help='corrected CSV to write')
    ap.add_argument('--moving', default='peg', help='moving object model name or file')
    ap.add_argument('--fixed', default='hole_block', help='fixed object model name or file')
    ap.add_argument('--fixed-pose', type=float, nargs=7, metavar='V',
                    help='fixed object pose x y z qx qy qz qw when the input has none '
                         '(default: identity)')
    ap.add_argument('--moving-topic', default='moving_pose', help='bag topic of moving poses')
    ap.add_argument('--fixed-topic', default=None, help='bag topic of fixed poses (optional)')
    ap.add_argument('--tolerance', type=float, default=0.002, help='contact distance [m]')
    ap.add_argument('--penetration-tolerance', type=float, default=None,
                    help='deepest penetration counted as contact [m] (default: tolerance)')
    ap.add_argument('--nonlinear-only', action='store_true',
                    help='skip the optimal linear correction')
    ap.add_argument('--figure', type=Path, default=None, help='write a Fig. 9-like PNG')
    return ap.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point; returns the process exit code (0 ok, 2 bad input)."""
    args = parse_args(argv)
    try:
        moving = load_polyhedron(args.moving)
        fixed = load_polyhedron(args.fixed)
        if args.input.is_dir():
            stamps, Tm, Tf = read_bag_poses(args.input, args.moving_topic, args.fixed_topic)
        else:
            stamps, Tm, Tf = read_csv(args.input)
    except (ValueError, FileNotFoundError, OSError, RuntimeError) as exc:
        print(f'correct_trajectory: error: {exc}', file=sys.stderr)
        return 2
    if Tf is None:
        Tf = np.broadcast_to(_pose(args.fixed_pose) if args.fixed_pose else np.eye(4),
                             Tm.shape).copy()
    opts = dict(tolerance=args.tolerance, penetration_tolerance=args.penetration_tolerance)
    results = correct_trajectory(moving, fixed, Tm, Tf, optimal=not args.nonlinear_only,
                                 **opts)
    write_csv(args.output, stamps, results)
    n_ok = sum(r.corrected for r in results)
    print(f'correct_trajectory: {n_ok} of {len(results)} frames corrected -> {args.output}')
    for k, r in enumerate(results):
        if not r.corrected and 'no contact' not in r.status:
            print(f'  frame {k}: {r.status}', file=sys.stderr)
    if args.figure is not None:
        nl = results if args.nonlinear_only else correct_trajectory(
            moving, fixed, Tm, Tf, optimal=False, **opts)
        plot_fig9(args.figure, stamps, list(Tm), list(Tf), nl, results)
        print(f'correct_trajectory: figure -> {args.figure}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
