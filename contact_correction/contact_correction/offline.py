"""
``correct_trajectory``: offline contact-based correction of a recorded trajectory.

Input, either
  - a CSV file with this header (one row per frame; ``#`` lines are comments; poses in a common
    frame, metres, unit quaternions in ROS order x, y, z, w)::

        stamp_ns,x,y,z,qx,qy,qz,qw[,fixed_x,fixed_y,fixed_z,fixed_qx,fixed_qy,fixed_qz,fixed_qw]

    ``x..qw`` is the observed pose of the moving object; the optional ``fixed_*`` columns give
    the fixed object's pose per frame (otherwise ``--fixed-pose``, default identity); or
  - a rosbag2 bag with the moving object's poses on ``--moving-topic``
    (geometry_msgs/PoseStamped, or nav_msgs/Path whose last message is used) and optionally the
    fixed object's on ``--fixed-topic`` (the newest one before each moving pose is used).

Relations: recognised by default (model selection against the stated pose noise
``--sigma-translation`` / ``--sigma-rotation-deg`` and a Viterbi temporal model over the
track, :mod:`contact_correction.recognition`); ``--relation`` gives it explicitly (the same
for every frame); ``--per-frame-detection`` detects it per frame with ``--tolerance`` (the
first version's behaviour).

Output: a CSV (``--output``), plain header on the first line::

    stamp_ns,x,y,z,qx,qy,qz,qw,corrected,method,rotation_rank,constraint_rank,pairs,
    penetration_observed_m,penetration_after_m,max_residual_m,dx,dy,dz,relation_source,status

(corrected pose in the input frame, metres, quaternion x y z w; ``dx, dy, dz`` = change of the
moving origin in the fixed object's frame [m]), and with ``--figure`` a PNG like the chapter's
Fig. 9: the observed and corrected trajectories, the correction along each frame's own
constrained and free directions (non-linear step only and non-linear + optimal; frames passed
through are marked), and the relation's rank per frame.
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

from .contact_relation import parse_relation, relative_pose
from .correction import CorrectionResult
from .nonlinear_correction import RESIDUAL_TOLERANCE
from .polyhedron import check_model_units, load_polyhedron
from .recognition import RecognitionOptions
from .trajectory import correct_trajectory

__all__ = ['read_csv', 'write_csv', 'read_bag_poses', 'plot_fig9', 'main']

POSE_COLUMNS = ['x', 'y', 'z', 'qx', 'qy', 'qz', 'qw']
FIXED_COLUMNS = ['fixed_' + c for c in POSE_COLUMNS]
OUTPUT_COLUMNS = ['stamp_ns', *POSE_COLUMNS, 'corrected', 'method', 'rotation_rank',
                  'constraint_rank', 'pairs', 'penetration_observed_m', 'penetration_after_m',
                  'max_residual_m', 'dx', 'dy', 'dz', 'relation_source', 'status']


def _pose(values: Sequence[float]) -> np.ndarray:
    v = np.asarray(values, dtype=float)
    return make_transform(matrix_from_quaternion(v[3:7]), v[:3])


def _row(T: np.ndarray) -> List[float]:
    return [*T[:3, 3].tolist(), *quaternion_from_matrix(T[:3, :3]).tolist()]


def read_csv(path: Path) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray]]:
    """
    Read a trajectory CSV (see module docstring).

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
    """Read moving poses (and fixed poses, newest before each moving one) from a rosbag2 bag."""
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
        w = csv.writer(fh)
        w.writerow(OUTPUT_COLUMNS)
        for s, r in zip(stamps, results):
            T = np.asarray(r.T_moving, dtype=float).reshape(4, 4)
            pose = _row(T) if np.all(np.isfinite(T)) else [float('nan')] * 7
            w.writerow([int(s), *[f'{v:.9g}' for v in pose], int(r.corrected), r.method,
                        r.rotation_rank, r.constraint_rank, len(r.pairs),
                        f'{r.penetration_before:.6g}', f'{r.penetration_after:.6g}',
                        f'{r.max_residual:.6g}',
                        *[f'{v:.9g}' for v in r.translation_change], r.relation_source,
                        r.status])


def plot_fig9(path: Path, stamps: np.ndarray, observed: np.ndarray, fixed: np.ndarray,
              nonlinear: Sequence[CorrectionResult], optimal: Sequence[CorrectionResult]
              ) -> None:
    """
    Fig. 9-like figure of a corrected track.

    Each frame's correction is split along the constrained and free translation directions of
    *that frame's own* relation (the relation changes along a track: sliding, inserted, pulled
    out), for the non-linear step only and for non-linear + optimal; the optimal correction
    along the free directions is zero. Frames passed through are marked on every panel.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    def origin_in_fixed(Ts: Sequence[np.ndarray]) -> np.ndarray:
        return np.array([relative_pose(T, F)[:3, 3] if np.all(np.isfinite(T)) else
                         np.full(3, np.nan) for F, T in zip(fixed, Ts)])

    obs = origin_in_fixed(observed)
    nl = origin_in_fixed([r.T_moving for r in nonlinear])
    op = origin_in_fixed([r.T_moving for r in optimal])
    n = len(obs)
    con = {'nl': np.full(n, np.nan), 'op': np.full(n, np.nan)}
    free = {'nl': np.full(n, np.nan), 'op': np.full(n, np.nan)}
    for k, r in enumerate(optimal):
        d = r.directions
        if not r.corrected or d is None:
            continue
        for key, pos in (('nl', nl), ('op', op)):
            delta = pos[k] - obs[k]
            if len(d.constrained_translation):
                con[key][k] = np.linalg.norm(d.constrained_translation @ delta) * 1e3
            free[key][k] = (np.linalg.norm(d.free_translation @ delta) * 1e3
                            if len(d.free_translation) else 0.0)
    passed = np.array([not r.corrected for r in optimal], dtype=bool)
    t = (stamps - stamps[0]) * 1e-9 if len(stamps) else np.zeros(0)

    def mark(a) -> None:
        if np.any(passed):
            a.plot(t[passed], np.zeros(np.count_nonzero(passed)), 'x', color='0.4', ms=5,
                   label='passed through')

    fig, ax = plt.subplots(2, 2, figsize=(11, 8))
    for a, series, optimal_label, title in (
            (ax[0, 0], con, 'non-linear + optimal',
             "|correction| along each frame's constrained translations"),
            (ax[0, 1], free, 'non-linear + optimal (0)',
             "|change| along each frame's free translations")):
        a.plot(t, series['nl'], 'r.-', lw=1, alpha=0.6, label='non-linear only')
        a.plot(t, series['op'], 'b.--', lw=1, label=optimal_label)
        mark(a)
        a.set_title(title)
        a.set_xlabel('time [s]')
        a.set_ylabel('[mm]')
        a.legend(fontsize=8)
    a = ax[1, 0]
    a.plot(obs[:, 0] * 1e3, obs[:, 1] * 1e3, 'k.', ms=3, label='observed')
    a.plot(op[:, 0] * 1e3, op[:, 1] * 1e3, 'b-', lw=1, label='non-linear + optimal')
    if np.any(passed):
        a.plot(obs[passed, 0] * 1e3, obs[passed, 1] * 1e3, 'x', color='0.4', ms=5,
               label='passed through')
    a.set_xlabel('x (fixed frame) [mm]')
    a.set_ylabel('y (fixed frame) [mm]')
    a.set_aspect('equal', adjustable='datalim')
    a.set_title('trajectory projected on the xy-plane')
    a.legend(fontsize=8)
    a = ax[1, 1]
    a.step(t, [r.constraint_rank for r in optimal], 'b-', where='mid',
           label='constraint rank (Eq. 2)')
    a.step(t, [r.rotation_rank for r in optimal], 'g--', where='mid',
           label='rotation rank (Eq. 3)')
    mark(a)
    a.set_ylim(-0.5, 6.5)
    a.set_title("each frame's relation")
    a.set_xlabel('time [s]')
    a.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """Command-line options (defaults shown by ``--help``)."""
    ap = argparse.ArgumentParser(
        prog='correct_trajectory',
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description='Correct a recorded moving-object trajectory with contact relations '
                    '(chapter Section 3) and write the corrected CSV (+ a Fig. 9-like plot). '
                    'Poses and models in metres.')
    ap.add_argument('input', type=Path, help='trajectory CSV or rosbag2 bag directory')
    ap.add_argument('-o', '--output', type=Path, required=True, help='corrected CSV to write')
    ap.add_argument('--moving', default=None,
                    help='moving object model name or file (not given: the shipped peg, '
                         'with a notice)')
    ap.add_argument('--fixed', default=None,
                    help='fixed object model name or file (not given: the shipped '
                         'hole_block, with a notice)')
    ap.add_argument('--fixed-pose', type=float, nargs=7, metavar='V',
                    help='fixed object pose x y z qx qy qz qw when the input has none '
                         '(not given: identity)')
    ap.add_argument('--moving-topic', default='moving_pose', help='bag topic of moving poses')
    ap.add_argument('--fixed-topic', default=None, help='bag topic of fixed poses (optional)')
    g = ap.add_argument_group('relation')
    g.add_argument('--relation', default=None,
                   help="explicit relation for every frame, e.g. 'vertex 0 - face 4; face 2 - "
                        "vertex 15' (element indices of the loaded models)")
    g.add_argument('--per-frame-detection', action='store_true',
                   help='detect the relation per frame with --tolerance (no model selection, '
                        'no temporal model)')
    g.add_argument('--online', action='store_true',
                   help='temporal model causal (as the node) instead of back-tracking the '
                        'whole track')
    g.add_argument('--sigma-translation', type=float, default=0.001,
                   help='stated pose noise, translation per axis [m]')
    g.add_argument('--sigma-rotation-deg', type=float, default=1.0,
                   help='stated pose noise, rotation per axis [deg]')
    g.add_argument('--search-margin', type=float, default=None,
                   help='candidate contact margin [m] (not given: 3 (sigma_t + sigma_r '
                        'size / 2))')
    g.add_argument('--free-dof-penalty', type=float, default=3.0,
                   help='recognition score cost per degree of freedom left free')
    g.add_argument('--switch-cost', type=float, default=5.0,
                   help='temporal model cost per contact switched on or off (on top of '
                        '--transition-cost)')
    g.add_argument('--transition-cost', type=float, default=15.0,
                   help='temporal model cost of a change of contact state, once per change')
    g.add_argument('--ambiguity-margin', type=float, default=5.0,
                   help='at a contact change the evidence does not pin down, enforce only the '
                        'contacts common to both relations when the other is within this '
                        'score margin (forward costs with --online, where a relation with '
                        'more constraints scoring better by over one free DOF penalty within '
                        'it is also taken up at once; 0: off)')
    g.add_argument('--evidence-chi2', type=float, default=9.0,
                   help="drop constraints of the temporal model's relation that the frame "
                        'rejects: a nested relation fitting better by more than this chi2 '
                        '(1 constraint; same tail probability for more) is used (0: off)')
    g.add_argument('--innovation-evidence-chi2', type=float, default=6.63,
                   help='with --online and --noise-correlation > 0: drop for a frame the '
                        'constraints the change since the previous frame rejects at this '
                        'level (a chi2 as --evidence-chi2; 6.63 = p 0.01; 0: off)')
    g.add_argument('--max-correction-sigma', type=float, default=4.0,
                   help='correction-size guard k: a correction over k sigma_translation or k '
                        'sigma_rotation is refused; relations with fewer constraints, then '
                        'only the penetration removed, are tried; flagged "guard" in the '
                        'status (0: off)')
    g.add_argument('--noise-correlation', type=float, default=0.0,
                   help='frame-to-frame correlation of the pose errors (AR(1) rho, [0, 1)): the '
                        'offline temporal model scores a held relation by the innovation of '
                        'its noise estimate (with --online: a contact the innovation rejects '
                        'at --innovation-evidence-chi2 is dropped for that frame; 0: '
                        'independent errors)')
    g.add_argument('--tolerance', type=float, default=0.002,
                   help='contact distance of --per-frame-detection [m]')
    g.add_argument('--penetration-tolerance', type=float, default=None,
                   help='deepest penetration counted as contact by --per-frame-detection [m] '
                        '(not given: tolerance)')
    c = ap.add_argument_group('correction limits')
    c.add_argument('--element-margin', type=float, default=1e-6,
                   help='largest distance of a corrected contact point outside its element '
                        '[m] (recognised relations: at least the search margin)')
    c.add_argument('--max-translation', type=float, default=0.02,
                   help='largest accepted correction of the moving origin [m]')
    c.add_argument('--max-rotation-deg', type=float, default=20.0,
                   help='largest accepted orientation correction [deg]')
    c.add_argument('--residual-tolerance', type=float, default=RESIDUAL_TOLERANCE,
                   help='contact residual accepted after correction [m]')
    c.add_argument('--reference-point', choices=('origin', 'centroid'), default='origin',
                   help='the point of the moving object the optimal correction keeps where it '
                        'was observed along the directions the relation leaves free: the '
                        "model's origin (the chapter) or its surface centroid (independent of "
                        "where the model's origin is; better for poses from a "
                        "surface-fitting localiser, whose errors tilt about the part's middle)")
    ap.add_argument('--nonlinear-only', action='store_true',
                    help='skip the optimal linear correction')
    ap.add_argument('--figure', type=Path, default=None, help='write a Fig. 9-like PNG')
    args = ap.parse_args(argv)
    for name in ('sigma_translation', 'sigma_rotation_deg', 'search_margin', 'free_dof_penalty',
                 'switch_cost', 'transition_cost', 'ambiguity_margin', 'evidence_chi2',
                 'innovation_evidence_chi2', 'max_correction_sigma', 'tolerance',
                 'penetration_tolerance', 'element_margin', 'max_translation',
                 'max_rotation_deg', 'residual_tolerance'):
        v = getattr(args, name)
        if v is not None and (not np.isfinite(v) or v < 0):
            ap.error(f'--{name.replace("_", "-")} must be a finite number >= 0, got {v}')
    if args.sigma_translation <= 0 or args.sigma_rotation_deg <= 0:
        ap.error('--sigma-translation and --sigma-rotation-deg must be > 0')
    if not (np.isfinite(args.noise_correlation) and 0.0 <= args.noise_correlation < 1.0):
        ap.error(f'--noise-correlation must be in [0, 1), got {args.noise_correlation}')
    return args


def _check_poses(Tm: np.ndarray, Tf: np.ndarray, size: float) -> List[str]:
    """
    Warn about poses implausible for metres.

    Warnings on poses implausible for metres (relative distances of hundreds of model
    sizes, e.g. millimetre poses with metre models).
    """
    rel = [np.linalg.norm(relative_pose(a, b)[:3, 3]) for a, b in zip(Tm, Tf)
           if np.all(np.isfinite(a)) and np.all(np.isfinite(b))]
    if rel and np.median(rel) > 100.0 * max(size, 1e-3):
        return [f'the moving object is {np.median(rel):.4g} m (median) from the fixed one, '
                f'{np.median(rel) / size:.0f}x its size: poses in millimetres?']
    return []


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Entry point; returns the process exit code (0 ok, 2 bad input)."""
    args = parse_args(argv)
    for opt, default in (('moving', 'peg'), ('fixed', 'hole_block')):
        if getattr(args, opt) is None:
            print(f'correct_trajectory: notice: no --{opt} given; using the shipped model '
                  f'{default!r}', file=sys.stderr)
            setattr(args, opt, default)
    try:
        moving = load_polyhedron(args.moving)
        fixed = load_polyhedron(args.fixed)
        for poly in (moving, fixed):
            for w in check_model_units(poly):
                print(f'correct_trajectory: warning: {w}', file=sys.stderr)
        relation = parse_relation(args.relation) if args.relation else None
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
    for w in _check_poses(Tm, Tf, moving.size):
        print(f'correct_trajectory: warning: {w}', file=sys.stderr)
    opts = {'tolerance': args.tolerance, 'penetration_tolerance': args.penetration_tolerance,
            'element_margin': args.element_margin, 'max_translation': args.max_translation,
            'max_rotation': float(np.deg2rad(args.max_rotation_deg)),
            'residual_tolerance': args.residual_tolerance,
            'reference_point': moving.centroid if args.reference_point == 'centroid' else None}
    recognition = None if (args.per_frame_detection or relation is not None) else \
        RecognitionOptions(sigma_translation=args.sigma_translation,
                           sigma_rotation=float(np.deg2rad(args.sigma_rotation_deg)),
                           search_margin=args.search_margin,
                           free_dof_penalty=args.free_dof_penalty,
                           switch_cost=args.switch_cost,
                           transition_cost=args.transition_cost,
                           ambiguity_margin=args.ambiguity_margin,
                           evidence_chi2=args.evidence_chi2,
                           innovation_evidence_chi2=args.innovation_evidence_chi2,
                           max_correction_sigma=args.max_correction_sigma,
                           noise_correlation=args.noise_correlation)
    relations = [relation] * len(Tm) if relation is not None else None
    try:
        results = correct_trajectory(moving, fixed, Tm, Tf, relations=relations,
                                     recognition=recognition, smooth=not args.online,
                                     optimal=not args.nonlinear_only, **opts)
    except ValueError as exc:
        print(f'correct_trajectory: error: {exc}', file=sys.stderr)
        return 2
    write_csv(args.output, stamps, results)
    n_ok = sum(r.corrected for r in results)
    n_guard = sum(r.guarded for r in results)
    print(f'correct_trajectory: {n_ok} of {len(results)} frames corrected -> {args.output}'
          + (f'; {n_guard} guarded (a correction beyond --max-correction-sigma refused, see '
             'the status column)' if n_guard else ''))
    for k, r in enumerate(results):
        if not r.corrected and 'no contact' not in r.status:
            print(f'  frame {k}: {r.status}', file=sys.stderr)
    if args.figure is not None:
        # the non-linear step alone, with the same relations
        nl_rel = [list(r.pairs) if r.corrected else None for r in results]
        nl = results if args.nonlinear_only else correct_trajectory(
            moving, fixed, Tm, Tf, relations=[p if p else [] for p in nl_rel], optimal=False,
            **dict(opts, element_margin=max(args.element_margin, 0.02)))
        plot_fig9(args.figure, stamps, list(Tm), list(Tf), nl, results)
        print(f'correct_trajectory: figure -> {args.figure}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
