"""
Offline export of synthetic stereo sequences to files (no ROS needed).

``python -m stereo_depth.synthetic.export --scene peg_in_hole --frames 0:225:5 --out DIR``
writes, per frame k: ``left_<k>.png``, ``right_<k>.png`` (mono8 or rgb8) and ``truth_<k>.npz``
(depth [m] and disparity [px] float32 with NaN background, occlusion bool, object_id int16,
face_id int32, texcoords float32); for the sequence: ``poses.csv`` (frame, time_s, object,
x y z [m], qx qy qz qw: object pose in the left optical frame, contact_phase) and
``camera.yaml`` (K, baseline, P_left, P_right, image size, object names).
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
import sys
from typing import List, Optional, Sequence

import cv2
import numpy as np

from stereo_manip_tools.transforms import quaternion_from_matrix

from . import RenderOptions, SCENES, StereoCamera, SyntheticStereo

__all__ = ['export_sequence', 'main', 'parse_frames']


def parse_frames(spec: str) -> List[int]:
    """
    ``'10'`` -> [10]; ``'a:b'`` / ``'a:b:s'`` -> range(a, b, s).

    :raises ValueError: for a malformed or empty specification.
    """
    parts = spec.split(':')
    try:
        nums = [int(p) for p in parts]
    except ValueError:
        raise ValueError(f'frames must be N or START:STOP[:STEP], got {spec!r}') from None
    if len(nums) == 1:
        frames = nums
    elif len(nums) in (2, 3):
        frames = list(range(*nums))
    else:
        raise ValueError(f'frames must be N or START:STOP[:STEP], got {spec!r}')
    if not frames or min(frames) < 0:
        raise ValueError(f'frames {spec!r} select nothing or a negative index')
    return frames


def export_sequence(stereo: SyntheticStereo, frames: Sequence[int], out: Path) -> int:
    """Write the frames of ``stereo`` to ``out`` (created); returns the number written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cam = stereo.camera
    with open(out / 'camera.yaml', 'w', encoding='utf-8') as fh:
        fh.write(f'# synthetic stereo camera, scene {stereo.scene.name}, seed '
                 f'{stereo.scene.seed}\n')
        fh.write(f'width: {cam.width}\nheight: {cam.height}\nbaseline: {cam.baseline}\n')
        for key in ('K', 'P_left', 'P_right'):
            fh.write(f'{key}: {json.dumps(getattr(cam, key).ravel().tolist())}\n')
        fh.write(f'objects: {json.dumps(list(stereo.scene.objects))}\n')
    with open(out / 'poses.csv', 'w', newline='', encoding='utf-8') as fh:
        w = csv.writer(fh)
        w.writerow(['frame', 'time_s', 'object', 'x', 'y', 'z', 'qx', 'qy', 'qz', 'qw',
                    'contact_phase'])
        for k in frames:
            left, right, truth = stereo.render(k)
            for name, img in (('left', left), ('right', right)):
                im = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
                cv2.imwrite(str(out / f'{name}_{k:06d}.png'), im)
            np.savez_compressed(out / f'truth_{k:06d}.npz', depth=truth['depth'],
                                disparity=truth['disparity'], occlusion=truth['occlusion'],
                                object_id=truth['object_id'], face_id=truth['face_id'],
                                texcoords=truth['texcoords'])
            for name, T in truth['poses'].items():
                q = quaternion_from_matrix(T[:3, :3])
                w.writerow([k, f'{truth["time"]:.6f}', name,
                            *[f'{x:.9f}' for x in T[:3, 3]], *[f'{x:.9f}' for x in q],
                            truth.get('contact_phase', '')])
    return len(frames)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description='Export a synthetic stereo sequence to files.')
    ap.add_argument('--scene', default='peg_in_hole', choices=SCENES)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--frames', default='0:30', help='N or START:STOP[:STEP]')
    ap.add_argument('--out', required=True, help='output directory')
    ap.add_argument('--rgb', action='store_true', help='rgb8 images instead of mono8')
    ap.add_argument('--fx', type=float, default=600.0, help='focal length [px]')
    ap.add_argument('--baseline', type=float, default=0.10, help='baseline [m]')
    ap.add_argument('--noise', type=float, default=0.0, help='noise std [grey levels]')
    args = ap.parse_args(argv)
    try:
        frames = parse_frames(args.frames)
        cam = StereoCamera.create(fx=args.fx, baseline=args.baseline)
        opts = RenderOptions(color=args.rgb, noise_sigma=args.noise)
    except ValueError as exc:
        print(f'export: {exc}', file=sys.stderr)
        return 2
    n = export_sequence(SyntheticStereo(args.scene, args.seed, cam, opts), frames,
                        Path(args.out))
    print(f'wrote {n} frames of {args.scene} to {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
