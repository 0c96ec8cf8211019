"""
``estimate_joint``: offline joint estimation from a CSV file or a rosbag2 bag.

Input, one of:
  - ``--csv FILE`` with a header row: ``stamp`` [s] (optional) and either the relative pose
    of link A in link B, ``x y z qx qy qz qw`` [m, unit quaternion], or both links' poses in a
    common frame, ``a_x a_y a_z a_qx a_qy a_qz a_qw b_x b_y b_z b_qx b_qy b_qz b_qw``;
  - ``--bag DIR`` with geometry_msgs/PoseStamped topics: ``--topic-relative`` or
    ``--topic-a`` and ``--topic-b`` (paired by header stamp within ``--sync-tolerance``).
Defaults: noise levels estimated from the data (give ``--sigma-position`` and
``--sigma-rotation-deg`` for a known sensor), square-marker pose flips repaired with the
ambiguity twin (relative input: link B is the camera, link A the marker; two-link input: both
poses in the camera's frame; ``--no-flip-repair`` to turn off).
Output: a summary on stdout (warnings on stderr), ``--output`` JSON (parameters, candidates'
BIC, rejected and repaired frames, estimated noise, inlier coverage, axis uncertainty, warnings,
unwrapped joint coordinates), ``--figure`` PNG like the chapter's Fig. 13 (the track of link A's
origin in link B's frame and the estimated axis, from the side and the front, plus the joint
coordinate and residuals per frame), ``--corrected-csv`` (the corrected relative track).
Exit status 0 on success, 2 on bad input (message on stderr).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
import sys
from typing import Optional, Sequence

from joint_estimator.ambiguity import AXIS_INDEX, two_link_candidates
from joint_estimator.common import JointType, relative_track
from joint_estimator.selection import estimate_joint, JointEstimation
import numpy as np
from stereo_manip_tools.transforms import matrix_from_quaternion, quaternion_from_matrix

__all__ = ['read_csv_track', 'read_bag_track', 'estimation_to_dict', 'plot_estimation', 'main']

_POSE = ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')


def _poses_from_columns(cols: np.ndarray, where: str) -> np.ndarray:
    T = np.tile(np.eye(4), (cols.shape[0], 1, 1))
    for i, row in enumerate(cols):
        if not np.all(np.isfinite(row)):
            raise ValueError(f'{where}: row {i + 1} has a missing or non-finite value')
        T[i, :3, :3] = matrix_from_quaternion(row[3:7])
        T[i, :3, 3] = row[:3]
    return T


def read_csv_track(path: Path, with_links: bool = False) -> tuple:
    """
    Relative track ``^B T_A`` (N, 4, 4) and stamps [ns] (or None) from a CSV file.

    With ``with_links`` also the two links' tracks ``(A, B)`` in the common frame (None for a
    relative CSV).

    :raises ValueError: unreadable file, missing columns, non-numeric or non-finite values.
    """
    try:
        with open(path, newline='') as f:
            rows = [r for r in csv.reader(f) if r and not r[0].lstrip().startswith('#')]
    except OSError as exc:
        raise ValueError(f'cannot read {path}: {exc.strerror}') from exc
    if len(rows) < 2:
        raise ValueError(f'{path}: needs a header row and at least one pose row')
    header = [h.strip() for h in rows[0]]
    try:
        data = np.array([[float(v) if v.strip() else np.nan for v in r] for r in rows[1:]])
    except ValueError as exc:
        raise ValueError(f'{path}: non-numeric value ({exc})') from exc
    if data.ndim != 2 or data.shape[1] != len(header):
        raise ValueError(f'{path}: every row needs {len(header)} values like the header')
    col = {h: i for i, h in enumerate(header)}
    stamps = None
    if 'stamp' in col:
        stamps = np.round(data[:, col['stamp']] * 1e9).astype(np.int64)
    if all(k in col for k in _POSE):
        T = _poses_from_columns(data[:, [col[k] for k in _POSE]], str(path))
        return (T, stamps, None) if with_links else (T, stamps)
    a_cols, b_cols = [f'a_{k}' for k in _POSE], [f'b_{k}' for k in _POSE]
    if all(k in col for k in a_cols + b_cols):
        T_a = _poses_from_columns(data[:, [col[k] for k in a_cols]], f'{path} (link a)')
        T_b = _poses_from_columns(data[:, [col[k] for k in b_cols]], f'{path} (link b)')
        T = relative_track(T_a, T_b)
        return (T, stamps, (T_a, T_b)) if with_links else (T, stamps)
    raise ValueError(f'{path}: header must have columns {" ".join(_POSE)} (relative pose) or '
                     f'a_x ... a_qw and b_x ... b_qw (two links); found {" ".join(header)}')


def read_bag_track(path: Path, topic_relative: Optional[str], topic_a: Optional[str],
                   topic_b: Optional[str], sync_tolerance: float = 0.005,
                   with_links: bool = False) -> tuple:
    """
    Read a relative track and its stamps [ns] from a rosbag2 bag.

    Relative track and stamps [ns] from PoseStamped topics of a rosbag2 bag (with
    ``with_links``, also the paired links' tracks ``(A, B)``, None for a relative topic).

    :raises ValueError: bad bag, missing topic, wrong type, unusable pose.
    """
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import deserialize_message
    from stereo_manip_tools.bag_io import BagError, read_bag
    from stereo_manip_tools.conversions import pose_stamped_to_matrix
    from stereo_manip_tools.sync import StampSynchronizer

    topics = [topic_relative] if topic_relative else [topic_a, topic_b]
    if not all(topics):
        raise ValueError('give --topic-relative, or both --topic-a and --topic-b')
    sync = StampSynchronizer(('a', 'b'), int(round(sync_tolerance * 1e9)), queue_size=50)
    poses, stamps, links_a, links_b = [], [], [], []
    try:
        for m in read_bag(path, topics):
            if m.msgtype != 'geometry_msgs/msg/PoseStamped':
                raise ValueError(f'topic {m.topic} has type {m.msgtype}, expected '
                                 'geometry_msgs/msg/PoseStamped')
            T, stamp, _ = pose_stamped_to_matrix(deserialize_message(m.data, PoseStamped))
            if topic_relative:
                poses.append(T)
                stamps.append(stamp)
                continue
            pair = sync.add('a' if m.topic == topic_a else 'b', stamp, (T, stamp))
            if pair is not None:
                poses.append(relative_track(pair['a'][0][None], pair['b'][0][None])[0])
                stamps.append(max(pair['a'][1], pair['b'][1]))
                links_a.append(pair['a'][0])
                links_b.append(pair['b'][0])
    except BagError as exc:
        raise ValueError(str(exc)) from exc
    if not poses:
        raise ValueError(f'{path}: no (paired) poses on {", ".join(topics)}')
    out = (np.array(poses), np.array(stamps, dtype=np.int64))
    if not with_links:
        return out
    return out + ((np.array(links_a), np.array(links_b)) if links_a else None,)


def _finite_or_none(v: float):
    return float(v) if np.isfinite(v) else None


def estimation_to_dict(est: JointEstimation) -> dict:
    """
    JSON-ready summary of an estimation (metres, radians; NaN as null).

    ``coordinates`` are the joint coordinates per frame, angles unwrapped in frame order.
    """
    b = est.best
    return {
        'joint_type': b.joint_type.name.lower(),
        'axis_in_a': b.axis_in_a.tolist(), 'axis_in_b': b.axis_in_b.tolist(),
        'point_in_a': b.point_in_a.tolist(), 'point_in_b': b.point_in_b.tolist(),
        'rotation_residual_rms_rad': b.rotation_rms, 'position_residual_rms_m': b.position_rms,
        'sample_count': int(b.inliers.size), 'outlier_indices': b.outlier_indices.tolist(),
        'degenerate': b.degenerate,
        'candidate_bic': {t.name.lower(): f.score for t, f in est.candidates.items()},
        'not_scored': {t.name.lower(): m for t, m in est.failures.items()},
        'repaired_indices': b.repaired_indices.tolist(),
        'noise': {'sigma_position_m': b.sigma_position, 'sigma_rotation_rad': b.sigma_rotation,
                  'estimated': bool(b.scale_estimated),
                  'line_of_sight_ratio': float(b.extra.get('line_of_sight_noise_ratio', 1.0))},
        'coverage': {'inlier_range': [_finite_or_none(v) for v in b.coordinate_range],
                     'motion_range': [_finite_or_none(v) for v in b.motion_range],
                     'fraction': _finite_or_none(b.coverage)},
        'axis_uncertainty': {'axis_angle_std_in_a_rad': _finite_or_none(b.axis_angle_std_in_a),
                             'axis_angle_std_in_b_rad': _finite_or_none(b.axis_angle_std_in_b),
                             'axis_point_std_m': _finite_or_none(b.axis_point_std)},
        'minimum_norm_point_in_a': (b.extra['minimum_norm_point_in_a'].tolist()
                                    if 'minimum_norm_point_in_a' in b.extra else None),
        'minimum_norm_point_in_b': (b.extra['minimum_norm_point_in_b'].tolist()
                                    if 'minimum_norm_point_in_b' in b.extra else None),
        'warnings': list(b.warnings),
        'coordinates': b.coordinates.tolist(), 'status': est.status,
    }


def plot_estimation(raw: np.ndarray, est: JointEstimation, path: Path) -> None:
    """
    Figure like Fig. 13.

    Track of A's origin in B (raw dots, corrected line, rejected frames as crosses) with the
    estimated axis in red, side and front views, plus the joint coordinate and residuals per frame.
    Written with matplotlib's Agg backend.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    b = est.best
    p_raw, p_cor = raw[:, :3, 3], b.corrected[:, :3, 3]
    fig = plt.figure(figsize=(13, 8))
    for k, (elev, azim, title) in enumerate(((10, -60, 'side view'), (10, 30, 'front view'))):
        ax = fig.add_subplot(2, 2, k + 1, projection='3d')
        ends = None
        inl = b.inliers
        ax.scatter(*p_raw[inl].T, s=6, c='tab:blue', label='raw track (link A origin in B)')
        ax.scatter(*p_raw[~inl].T, s=30, c='k', marker='x', label='rejected frames')
        ax.plot(*p_cor.T, c='tab:green', lw=1.2, label='corrected track')
        if b.joint_type in (JointType.REVOLUTE, JointType.CYLINDRICAL, JointType.PRISMATIC):
            l, c = b.axis_in_b, b.point_in_b
            s = (p_cor - c) @ l
            half = max(0.5 * np.ptp(np.linalg.norm(p_cor - p_cor.mean(0), axis=1)), 0.05)
            ends = np.array([c + (s.min() - half) * l, c + (s.max() + half) * l])
            ax.plot(*ends.T, c='red', lw=2.5, label='estimated axis')
        elif b.joint_type == JointType.SPHERICAL:
            ax.scatter(*b.point_in_b, c='red', s=60, label='estimated centre')
        elif b.joint_type == JointType.PLANAR:
            m = p_cor.mean(0)
            ax.plot(*np.array([m, m + 0.1 * b.axis_in_b]).T, c='red', lw=2.5,
                    label='plane normal')
        pts = np.vstack([p_cor, p_raw[inl]] + ([ends] if ends is not None else []))
        mid = (pts.min(0) + pts.max(0)) / 2.0
        half_box = max(np.ptp(pts, axis=0).max() / 2.0, 0.01)
        ax.set_xlim(mid[0] - half_box, mid[0] + half_box)
        ax.set_ylim(mid[1] - half_box, mid[1] + half_box)
        ax.set_zlim(mid[2] - half_box, mid[2] + half_box)
        ax.set_box_aspect((1, 1, 1))
        ax.locator_params(nbins=4)
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel('x [m]')
        ax.set_ylabel('y [m]')
        ax.set_zlabel('z [m]')
        ax.set_title(f'{b.joint_type.name.lower()} joint, {title}')
        if k == 0:
            ax.legend(loc='upper left', fontsize=7)
    t = np.arange(raw.shape[0])
    ax = fig.add_subplot(2, 2, 3)
    if b.coordinates.shape[1]:
        is_angle = b.joint_type != JointType.PRISMATIC
        q = np.degrees(np.unwrap(b.coordinates[:, 0])) if is_angle else b.coordinates[:, 0] * 1e3
        ax.plot(t[b.inliers], q[b.inliers], '.-', label='corrected (inlier frames)')
        ax.plot(t[~b.inliers], q[~b.inliers], 'kx', label='rejected frames (projected)')
        ax.set_ylabel('joint angle [deg]' if is_angle else 'displacement [mm]')
        ax.legend(fontsize=8)
    ax.set_xlabel('frame')
    ax.set_title('joint coordinate')
    ax = fig.add_subplot(2, 2, 4)
    ax.semilogy(t, np.maximum(b.position_residuals * 1000.0, 1e-6), '.', label='position [mm]')
    ax.semilogy(t, np.maximum(np.degrees(b.rotation_residuals), 1e-6), '.',
                label='orientation [deg]')
    ax.set_xlabel('frame')
    ax.set_title('raw - corrected residual')
    ax.legend(fontsize=8)
    fig.suptitle(est.status[:160], fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _parse(argv: Optional[Sequence[str]]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog='estimate_joint', description=__doc__.strip().split('\n')[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.strip().split('\n', 2)[2])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument('--csv', type=Path, help='CSV track (see below)')
    src.add_argument('--bag', type=Path, help='rosbag2 bag directory')
    ap.add_argument('--topic-relative', help='PoseStamped topic of link A in link B')
    ap.add_argument('--topic-a', help='PoseStamped topic of link A (common frame)')
    ap.add_argument('--topic-b', help='PoseStamped topic of link B (common frame)')
    ap.add_argument('--sync-tolerance', type=float, default=0.005,
                    help='stamp pairing tolerance for --topic-a/--topic-b [s]')
    ap.add_argument('--joint-type', default='auto',
                    choices=['auto'] + [t.name.lower() for t in JointType])
    ap.add_argument('--sigma-position', type=float, default=None,
                    help='position noise std per axis [m] (default: estimated from the data)')
    ap.add_argument('--sigma-rotation-deg', type=float, default=None,
                    help='orientation noise std per axis [deg] (default: estimated)')
    ap.add_argument('--no-flip-repair', action='store_true',
                    help='do not repair square-marker pose flips with the ambiguity twin')
    ap.add_argument('--marker-normal-axis', choices=sorted(AXIS_INDEX), default='z',
                    help="marker frame axis that is the marker's normal (ArUco: z)")
    ap.add_argument('--marker-side', type=float, default=None,
                    help="the square marker's side [m] (per-frame marker noise model; "
                         'default: estimated from the track)')
    ap.add_argument('--no-marker-weights', action='store_true',
                    help="do not refit a revolute joint with each frame's marker-pose noise")
    ap.add_argument('--no-robust', action='store_true', help='do not reject outlier frames')
    ap.add_argument('--no-refine', action='store_true',
                    help="chapter's Eqs. 17-18 only (no maximum-likelihood refinement)")
    ap.add_argument('--correction', choices=['ml', 'chapter'], default='ml')
    ap.add_argument('--output', type=Path, help='write the estimate as JSON')
    ap.add_argument('--figure', type=Path, help='write a Fig. 13-like PNG')
    ap.add_argument('--corrected-csv', type=Path, help='write the corrected relative track')
    return ap.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Command-line entry point; returns the exit status."""
    args = _parse(argv)
    try:
        if args.csv is not None:
            poses, stamps, links = read_csv_track(args.csv, with_links=True)
        else:
            poses, stamps, links = read_bag_track(args.bag, args.topic_relative, args.topic_a,
                                                  args.topic_b, args.sync_tolerance,
                                                  with_links=True)
        jt = None if args.joint_type == 'auto' else int(JointType[args.joint_type.upper()])
        for name, v in (('--sigma-position', args.sigma_position),
                        ('--sigma-rotation-deg', args.sigma_rotation_deg),
                        ('--marker-side', args.marker_side)):
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f'{name} must be positive, got {v}')
        axis = AXIS_INDEX[args.marker_normal_axis]
        flip = not args.no_flip_repair
        candidates = (two_link_candidates(links[0], links[1], axis)
                      if flip and links is not None else None)
        est = estimate_joint(
            poses, joint_type=jt, sigma_position=args.sigma_position,
            sigma_rotation=(None if args.sigma_rotation_deg is None
                            else np.deg2rad(args.sigma_rotation_deg)),
            robust=not args.no_robust, refine=not args.no_refine, correction=args.correction,
            stamps_ns=stamps, flip_repair=flip, marker_normal_axis=axis,
            pose_candidates=candidates, camera_noise=links is None,
            marker_weights=not args.no_marker_weights, marker_side=args.marker_side)
    except ValueError as exc:
        print(f'estimate_joint: {exc}', file=sys.stderr)
        return 2
    summary = estimation_to_dict(est)
    print(est.status)
    b = est.best
    print(f'axis in A {np.round(b.axis_in_a, 6).tolist()}  '
          f'in B {np.round(b.axis_in_b, 6).tolist()}')
    print(f'point in A {np.round(b.point_in_a, 6).tolist()} m  in B '
          f'{np.round(b.point_in_b, 6).tolist()} m')
    print(f'RMS residual: {b.position_rms * 1000:.3f} mm, {np.degrees(b.rotation_rms):.3f} deg '
          f'over {int(b.inliers.sum())} of {b.inliers.size} frames')
    for w in b.warnings:
        print(f'estimate_joint: WARNING: {w}', file=sys.stderr)
    if args.output:
        args.output.write_text(json.dumps(summary, indent=2) + '\n')
    if args.figure:
        plot_estimation(poses, est, args.figure)
    if args.corrected_csv:
        with open(args.corrected_csv, 'w', newline='') as f:
            w = csv.writer(f)
            w.writerow((['stamp'] if stamps is not None else []) + list(_POSE))
            for i, T in enumerate(b.corrected):
                row = list(T[:3, 3]) + list(quaternion_from_matrix(T[:3, :3]))
                w.writerow(([f'{stamps[i] / 1e9:.9f}'] if stamps is not None else [])
                           + [f'{v:.9g}' for v in row])
    return 0


if __name__ == '__main__':
    sys.exit(main())
