#!/usr/bin/env python3
"""
Benchmark of the stereo_depth pipeline against OpenCV StereoSGBM, measured in the same run.

1. Middlebury Motorcycle (scikit-image copy, 741x500, 64 disparities; the ground truth spans
   7.2-59.9 px, so 64 candidates cover it): non-occluded bad-1/2/4 with missing estimates counted
   as errors, invalid fraction, average error, and time per frame of every method. The
   non-occluded mask is derived from the left ground truth by z-buffer forward warping
   (``stereo_depth.evaluation.nonoccluded_mask``). Times are medians over interleaved
   repetitions (every method once per round), so all methods see the same machine load.
2. Frame rate at 640x480 with 64 disparities: each method on a stream of consecutive
   synthetic ``peg_in_hole`` frames, one method at a time, as the node would run it.
3. Synthetic ``peg_in_hole`` frames with exact truth (640x480; the scene's disparities reach
   126 px, so 128 candidates): bad-2 over visible (non-occluded) surface pixels, and the
   fraction of those pixels whose depth is within 1 % of the true depth.

Goals (issue 4): best own method's bad-2 <= 0.5 x SGBM_3WAY's; that method's time <= 3 x
SGBM_3WAY's; a real-time method >= 30 frames/s at 640x480, 64 disparities. When the most
accurate own method is not the node's default (``block_matching``), the two Motorcycle goals
are also reported for the default. Wall times are the goals; CPU times and the load average
are recorded because the machine is shared with other jobs.

Run: ``python bench/stereo_middlebury.py [--quick]`` (--quick: fewer repetitions/frames, for
trying things out; the committed JSON comes from a full run).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

from stereo_depth.evaluation import evaluate_disparity, nonoccluded_mask
from stereo_depth.pipeline import compute_disparity, method_defaults
from stereo_manip_tools.bench_report import goal, write_report

OWN = ['block_matching', 'sgm', 'sgm4', 'bp']
OPENCV = ['opencv_sgbm_3way', 'opencv_sgbm', 'opencv_bm']
BASELINE = 'opencv_sgbm_3way'


def run_method(name: str, left: np.ndarray, right: np.ndarray, ndisp: int) -> np.ndarray:
    if name == 'opencv_sgbm_3way':
        return compute_disparity(left, right, 'opencv_sgbm', ndisp, block_size=5, mode='3way')
    if name == 'opencv_sgbm':
        return compute_disparity(left, right, 'opencv_sgbm', ndisp, block_size=5, mode='sgbm')
    return compute_disparity(left, right, name, ndisp)


def timed_rounds(methods, left, right, ndisp, rounds, slow=('bp',)):
    """
    Median wall and CPU seconds per frame, methods interleaved round by round.

    Every method is called once before timing (numba cache load etc.), except the ``slow``
    ones, which run once, timed. CPU time (all threads of this process) is reported next to
    wall time because the machine is shared: it shows what the work costs without the load.
    """
    wall = {m: [] for m in methods}
    cpu = {m: [] for m in methods}
    out = {}
    for m in methods:
        if m not in slow:
            out[m] = run_method(m, left, right, ndisp)
    for r in range(rounds):
        for m in methods:
            if m in slow and r > 0:
                continue
            t0, c0 = time.perf_counter(), time.process_time()
            out[m] = run_method(m, left, right, ndisp)
            wall[m].append(time.perf_counter() - t0)
            cpu[m].append(time.process_time() - c0)
    return ({m: float(np.median(v)) for m, v in wall.items()},
            {m: float(np.median(v)) for m, v in cpu.items()}, out)


def middlebury(rounds: int) -> dict:
    import skimage.data

    left, right, gt = skimage.data.stereo_motorcycle()
    mask = nonoccluded_mask(gt)
    methods = OPENCV + OWN
    # BP (seconds per frame, ~0.5 GB of messages) runs once, after the interleaved rounds of
    # the others: its huge allocations leave the allocator in a state that slows every later
    # small-array method in this process, which would bias their times.
    fast = [m for m in methods if m != 'bp']
    times, cpu, outs = timed_rounds(fast, left, right, 64, rounds)
    t_bp, c_bp, out_bp = timed_rounds(['bp'], left, right, 64, 1)
    times.update(t_bp)
    cpu.update(c_bp)
    outs.update(out_bp)
    res = {}
    for m in methods:
        nonocc = evaluate_disparity(outs[m], gt, mask)
        allpix = evaluate_disparity(outs[m], gt)
        res[m] = {'time_s': times[m], 'cpu_s': cpu[m], 'nonocc': nonocc, 'all': allpix}
        print(f'{m:18s} {times[m] * 1e3:8.1f} ms (cpu {cpu[m] * 1e3:7.1f} ms)  nonocc bad-2 '
              f"{nonocc['bad-2.0']:.4f} "
              f"(invalid {nonocc['invalid']:.4f})  all bad-2 {allpix['bad-2.0']:.4f}",
              flush=True)
    return {'image_size': [int(gt.shape[1]), int(gt.shape[0])], 'num_disparities': 64,
            'gt_disparity_range': [float(np.nanmin(gt)), float(np.nanmax(gt))],
            'nonoccluded_fraction_of_image': float(mask.mean()),
            'mask_rule': 'z-buffer forward warping of the left GT, nearest column, 1 px '
                         'tolerance (stereo_depth.evaluation.nonoccluded_mask)',
            'methods': res}


def frame_rate(n_frames: int) -> dict:
    """
    Frames/s of each method on a stream.

    ``n_frames`` consecutive synthetic frames, one method at a time (as the node runs), after two
    warm-up frames; median per-frame time.
    """
    from stereo_depth.synthetic import render

    stream = [render('peg_in_hole', 60 + k)[:2] for k in range(n_frames)]
    methods = ['opencv_bm', 'opencv_sgbm_3way', 'block_matching', 'sgm4', 'sgm']
    fps, cpu = {}, {}
    for m in methods:
        for left, right in stream[:2]:
            run_method(m, left, right, 64)
        wall_t, cpu_t = [], []
        for left, right in stream:
            t0, c0 = time.perf_counter(), time.process_time()
            run_method(m, left, right, 64)
            wall_t.append(time.perf_counter() - t0)
            cpu_t.append(time.process_time() - c0)
        fps[m] = 1.0 / float(np.median(wall_t))
        cpu[m] = float(np.median(cpu_t))
        print(f'{m:18s} {fps[m]:7.1f} frames/s at 640x480, 64 disparities (cpu '
              f'{cpu[m] * 1e3:.1f} ms/frame)', flush=True)
    left = stream[0][0]
    return {'image_size': [int(left.shape[1]), int(left.shape[0])], 'num_disparities': 64,
            'frames': n_frames, 'fps': fps, 'cpu_s_per_frame': cpu,
            'load_average_after': list(os.getloadavg())}


def synthetic(frames, rounds: int) -> dict:
    from stereo_depth.synthetic import render

    methods = ['opencv_sgbm_3way', 'block_matching', 'sgm', 'sgm4']
    acc = {m: {'bad-2.0': [], 'invalid': [], 'depth_within_1pct': [], 'time_s': []}
           for m in methods}
    for k in frames:
        left, right, truth = render('peg_in_hole', k)
        cam = truth['camera']
        fx = float(np.asarray(cam['K'])[0, 0])
        baseline = float(cam['baseline'])
        visible = truth['valid'] & ~truth['occlusion']
        times, _, outs = timed_rounds(methods, left, right, 128, rounds)
        for m in methods:
            d = outs[m]
            e = evaluate_disparity(d, truth['disparity'], visible)
            with np.errstate(invalid='ignore', divide='ignore'):
                z = fx * baseline / d
            zt = truth['depth']
            ok = np.abs(z - zt) <= 0.01 * zt
            acc[m]['bad-2.0'].append(e['bad-2.0'])
            acc[m]['invalid'].append(e['invalid'])
            acc[m]['depth_within_1pct'].append(float(ok[visible].mean()))
            acc[m]['time_s'].append(times[m])
    res = {m: {k: float(np.mean(v)) for k, v in a.items()} for m, a in acc.items()}
    for m, r in res.items():
        print(f"{m:18s} peg_in_hole bad-2 {r['bad-2.0']:.4f} depth within 1 % "
              f"{r['depth_within_1pct']:.4f}  {r['time_s'] * 1e3:.1f} ms", flush=True)
    return {'scene': 'peg_in_hole', 'frames': list(frames), 'image_size': [640, 480],
            'num_disparities': 128, 'methods': res,
            'mask': "truth['valid'] & ~truth['occlusion'] (renderer's exact occlusion)"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='fewer repetitions and frames')
    args = ap.parse_args()
    rounds = 3 if args.quick else 7
    frames = [30, 120] if args.quick else [0, 30, 60, 90, 120, 150, 180, 210]

    fr = frame_rate(10 if args.quick else 30)       # first: a fresh process, like the node
    mb = middlebury(rounds)
    syn = synthetic(frames, 1 if args.quick else 3)

    base = mb['methods'][BASELINE]
    best = min(OWN, key=lambda m: mb['methods'][m]['nonocc']['bad-2.0'])
    default = 'block_matching'     # stereo_depth_node's default method

    def ratios(m):
        r = mb['methods'][m]
        return (r['nonocc']['bad-2.0'] / base['nonocc']['bad-2.0'], r['time_s'] / base['time_s'])

    fastest = max(fr['fps'], key=fr['fps'].get)
    fastest_own = max((m for m in fr['fps'] if not m.startswith('opencv')), key=fr['fps'].get)
    goals = [
        goal(f'motorcycle nonocc bad-2.0 of best own method ({best}) / SGBM_3WAY', 0.5, '<=',
             ratios(best)[0]),
        goal(f'motorcycle time per frame of best own method ({best}) / SGBM_3WAY', 3.0, '<=',
             ratios(best)[1]),
    ]
    if default != best:
        goals += [
            goal(f'motorcycle nonocc bad-2.0 of {default} (node default) / SGBM_3WAY', 0.5,
                 '<=', ratios(default)[0]),
            goal(f'motorcycle time per frame of {default} (node default) / SGBM_3WAY', 3.0,
                 '<=', ratios(default)[1]),
        ]
    goals += [
        goal(f'frames/s at 640x480, 64 disparities, fastest method ({fastest})', 30.0, '>=',
             fr['fps'][fastest]),
        goal(f'frames/s at 640x480, 64 disparities, fastest own method ({fastest_own})', 30.0,
             '>=', fr['fps'][fastest_own]),
    ]
    import cv2
    import numba

    write_report('stereo_middlebury', goals,
                 best_own_method=best,
                 method_parameters={m: {k: (list(v) if isinstance(v, tuple) else v)
                                        for k, v in method_defaults(m).items()}
                                    for m in OWN},
                 baseline=BASELINE + ' (block 5, P1=8*bs^2, P2=32*bs^2, 64 disparities)',
                 middlebury_motorcycle=mb, frame_rate_640x480=fr, synthetic_peg_in_hole=syn,
                 quick=bool(args.quick), numba_threads=int(numba.get_num_threads()),
                 opencv=cv2.__version__, numba=numba.__version__,
                 load_average=list(os.getloadavg()))


if __name__ == '__main__':
    main()
