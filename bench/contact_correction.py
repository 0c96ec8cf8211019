"""
Benchmark: vision error correction with contact relations (chapter Section 3, issue 5).

Ground-truth contact configurations on the shipped models (peg, hole_block, slot_block, table,
cube) are perturbed with pose noise sigma_t in {0.5, 1, 2, 5} mm and sigma_r in {0.5, 1, 2} deg
(rotation about the object origin, translation in the fixed frame), then corrected with the
true relation by (a) the non-linear step only (Takamatsu 2007; the baseline) and (b) non-linear +
optimal linear correction (Eqs. 2-9). Reported per method: contact residual, penetration, the
change of the translation along the free directions, the error vs truth along the constrained
and free translation directions (Fig. 9's decomposition), the rotation error along constrained
and free axes, time per frame; and the precision / recall of the detected contact relation.

Run: ``python bench/contact_correction.py`` (``--quick`` for a smoke run; the committed JSON
comes from a full run). Writes ``bench/results/contact_correction.json``.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
import sys
import time
from typing import Dict, List

# this script is named like the package it measures: keep its own directory off the import path
sys.path = [p for p in sys.path if Path(p or '.').resolve() != Path(__file__).resolve().parent]

from contact_correction.contact_relation import (  # noqa: E402
    detect_contact_relation, pair_key, penetration_depth)
from contact_correction.correction import correct_pose  # noqa: E402
from contact_correction.optimal_correction import (  # noqa: E402
    constraint_directions, constraint_matrix)
from contact_correction.polyhedron import load_polyhedron  # noqa: E402
import numpy as np  # noqa: E402
from stereo_manip_tools.bench_report import goal, write_report  # noqa: E402
from stereo_manip_tools.transforms import (  # noqa: E402
    make_transform, rotation_about_axis, rotation_log)

SIGMA_T = [0.5e-3, 1e-3, 2e-3, 5e-3]
SIGMA_R = [np.deg2rad(0.5), np.deg2rad(1.0), np.deg2rad(2.0)]
I4 = np.eye(4)


def rot(axis, angle):
    return rotation_about_axis(np.asarray(axis, dtype=float), angle)


def about_point(R, p):
    p = np.asarray(p, dtype=float)
    return make_transform(R, p - R @ p)


def configurations(models) -> Dict[str, tuple]:
    """Map a name to (moving, fixed, list of true relative poses)."""
    peg, cube, table = models['peg'], models['cube'], models['table']
    hole, slot = models['hole_block'], models['slot_block']
    out = {}
    half = cube.vertices[:, 2].max()
    out['face_face_resting'] = (cube, table,
                                [make_transform(rot([0, 0, 1], 0.3), [0.05, -0.02, half])])
    out['edge_on_face'] = (peg, table, [about_point(rot([1, 0, 0], 0.5), [0, -0.02, 0])])
    T = about_point(rot([1, -1, 0], 0.4), [0.0, 0.0, 0.0])
    T[2, 3] -= cube.transformed_vertices(T)[:, 2].min()
    out['vertex_on_face'] = (cube, table, [T])
    # peg lying across the hole block's top edge x = 0.08 (face on edge, Eq. 9)
    theta = 0.3
    R = rot([0, 1, 0], np.pi / 2 + theta)
    out['face_on_edge'] = (peg, hole, [make_transform(R, np.array([0.08, 0.0, 0.0])
                                                      - R @ [0.02, 0.0, 0.06])])
    out['peg_in_slot'] = (peg, slot, [make_transform(np.eye(3), [0.01, 0.0, -0.04])])
    out['peg_in_hole'] = (peg, hole, [make_transform(np.eye(3), [0.0, 0.0, -0.03])])
    # straight insertion: frames with the peg bottom from 0 (rim) down to 4 cm deep
    out['straight_insertion'] = (peg, hole, [make_transform(np.eye(3), [0.0, 0.0, -z])
                                             for z in np.linspace(0.005, 0.04, 8)])
    return out


def run(quick: bool) -> None:
    rng = np.random.default_rng(20261122)
    models = {n: load_polyhedron(n) for n in
              ('peg', 'cube', 'table', 'hole_block', 'slot_block')}
    cfgs = configurations(models)
    trials = 4 if quick else 20
    sig_t = SIGMA_T[2:3] if quick else SIGMA_T
    sig_r = SIGMA_R[1:2] if quick else SIGMA_R
    # warm-up (numba kernels)
    m, f, Ts = cfgs['peg_in_hole']
    correct_pose(m, f, Ts[0], I4)

    rows: List[dict] = []
    per_config: Dict[str, dict] = {}
    for name, (m, f, poses) in cfgs.items():
        info = {'pairs': [], 'rotation_rank': [], 'methods': set()}
        for T in poses:
            truth = detect_contact_relation(m, f, T, I4, tolerance=1e-7)
            A, g = constraint_matrix(m, f, T, truth)
            assert np.abs(g.distances).max() < 1e-12, name
            d_true = constraint_directions(A, m.size)
            info['pairs'].append(len(truth))
            info['rotation_rank'].append(d_true.rotation_rank)
            truth_keys = {pair_key(p) for p in truth}
            # contact centroid, in the moving body frame (a reference point on the contact)
            c_world = g.points.mean(0)
            c_body = T[:3, :3].T @ (c_world - T[:3, 3])
            for st in sig_t:
                for sr in sig_r:
                    for _ in range(trials):
                        w = rng.normal(size=3) * sr
                        T_obs = make_transform(rot(w, np.linalg.norm(w)) @ T[:3, :3],
                                               T[:3, 3] + rng.normal(size=3) * st)
                        row = {'config': name, 'sigma_t': st, 'sigma_r': sr,
                               'pairs': len(truth)}
                        for method, optimal in (('nonlinear', False), ('optimal', True)):
                            t0, c0 = time.perf_counter(), time.thread_time()
                            r = correct_pose(m, f, T_obs, I4, truth, optimal=optimal,
                                             check_penetration=False)
                            dt = time.perf_counter() - t0
                            dc = time.thread_time() - c0
                            pen = penetration_depth(m, f, r.T_moving, I4, spacing=0.002)
                            ok = r.corrected
                            d_out = r.directions
                            if not ok:
                                info.setdefault('failures', []).append(
                                    f'{method} sigma_t={st} sigma_r={sr:.4f}: {r.status}')
                                row[method] = {'corrected': False, 'time': dt, 'cpu': dc}
                                continue
                            dpos = r.T_moving[:3, 3] - T_obs[:3, 3]
                            drot = rotation_log(r.T_moving[:3, :3] @ T_obs[:3, :3].T)
                            err_t = r.T_moving[:3, 3] - T[:3, 3]
                            err_c = r.T_moving[:3, :3] @ c_body + r.T_moving[:3, 3] - c_world
                            err_r = rotation_log(r.T_moving[:3, :3] @ T[:3, :3].T)
                            row[method] = {
                                'corrected': ok, 'time': dt, 'cpu': dc,
                                'residual': r.max_residual,
                                'penetration': pen,
                                'free_change': float(np.abs(d_out.free_translation @ dpos).max())
                                if len(d_out.free_translation) else 0.0,
                                'free_rot_change': float(np.abs(d_out.free_rotation @ drot).max())
                                if len(d_out.free_rotation) else 0.0,
                                'err_con': float(np.linalg.norm(
                                    d_true.constrained_translation @ err_t)),
                                'err_free': float(np.linalg.norm(
                                    d_true.free_translation @ err_t)),
                                'err_con_contact': float(np.linalg.norm(
                                    d_true.constrained_translation @ err_c)),
                                'err_free_contact': float(np.linalg.norm(
                                    d_true.free_translation @ err_c)),
                                'rot_err_con': float(np.linalg.norm(
                                    d_true.constrained_rotation @ err_r)),
                                'rot_err_free': float(np.linalg.norm(
                                    d_true.free_rotation @ err_r)),
                            }
                            info['methods'].add(r.method)
                        e_t = T_obs[:3, 3] - T[:3, 3]
                        e_r = rotation_log(T_obs[:3, :3] @ T[:3, :3].T)
                        e_c = T_obs[:3, :3] @ c_body + T_obs[:3, 3] - c_world
                        row['observed'] = {
                            'err_con': float(np.linalg.norm(d_true.constrained_translation @ e_t)),
                            'err_free': float(np.linalg.norm(d_true.free_translation @ e_t)),
                            'err_con_contact': float(np.linalg.norm(
                                d_true.constrained_translation @ e_c)),
                            'err_free_contact': float(np.linalg.norm(
                                d_true.free_translation @ e_c)),
                            'rot_err_con': float(np.linalg.norm(
                                d_true.constrained_rotation @ e_r)),
                            'rot_err_free': float(np.linalg.norm(d_true.free_rotation @ e_r)),
                            'penetration': penetration_depth(m, f, T_obs, I4, spacing=0.002),
                        }
                        # full per-frame pipeline as the node runs it: detect, correct, check
                        tol = 3.0 * st + 3.0 * sr * m.size / 2.0
                        t0, c0 = time.perf_counter(), time.thread_time()
                        det = detect_contact_relation(m, f, T_obs, I4, tolerance=tol)
                        t_det = time.perf_counter() - t0
                        r_full = correct_pose(m, f, T_obs, I4, det, tolerance=tol)
                        row['pipeline_time'] = time.perf_counter() - t0
                        row['pipeline_cpu'] = time.thread_time() - c0
                        row['detect_time'] = t_det
                        keys = {pair_key(p) for p in det}
                        row['tp'] = len(keys & truth_keys)
                        row['fp'] = len(keys - truth_keys)
                        row['fn'] = len(truth_keys - keys)
                        row['detected_corrected'] = r_full.corrected
                        rows.append(row)
        info['methods'] = sorted(info['methods'])
        for line in info.get('failures', [])[:5]:
            print(f'{name}: passed through: {line}')
        per_config[name] = info
    summarise(rows, per_config, quick)


def _rms(x) -> float:
    x = np.asarray(list(x), dtype=float)
    x = x[np.isfinite(x)]      # frames the method passed through are counted separately
    return float(np.sqrt(np.mean(x ** 2))) if len(x) else float('nan')


def summarise(rows: List[dict], per_config: Dict[str, dict], quick: bool) -> None:
    by_method = {}
    for method in ('nonlinear', 'optimal'):
        ok = [r for r in rows if r[method]['corrected']]
        by_method[method] = {
            'frames': len(rows), 'corrected': len(ok),
            'max_residual_m': max(r[method]['residual'] for r in ok),
            'max_penetration_m': max(r[method]['penetration'] for r in ok),
            'max_free_translation_change_m': max(r[method]['free_change'] for r in ok),
            'max_free_rotation_change_rad': max(r[method]['free_rot_change'] for r in ok),
            'mean_wall_time_ms': 1e3 * float(np.mean([r[method]['time'] for r in rows])),
            'mean_cpu_time_ms': 1e3 * float(np.mean([r[method]['cpu'] for r in rows])),
        }
    # error decomposition per config and sigma_t (pooled over sigma_r)
    table = {}
    for cfg in per_config:
        table[cfg] = {}
        for st in sorted({r['sigma_t'] for r in rows}):
            sel = [r for r in rows if r['config'] == cfg and r['sigma_t'] == st]
            if not sel:
                continue
            ent = {}
            for key in ('observed', 'nonlinear', 'optimal'):
                ent[key] = {k: _rms(r[key].get(k, np.nan) for r in sel)
                            for k in ('err_con', 'err_free', 'err_con_contact',
                                      'err_free_contact', 'rot_err_con', 'rot_err_free')}
            ent['constrained_reduction_optimal'] = (ent['observed']['err_con']
                                                    / max(ent['optimal']['err_con'], 1e-300))
            ent['constrained_reduction_optimal_at_contact'] = (
                ent['observed']['err_con_contact']
                / max(ent['optimal']['err_con_contact'], 1e-300))
            ent['constrained_reduction_nonlinear'] = (ent['observed']['err_con']
                                                      / max(ent['nonlinear']['err_con'], 1e-300))
            table[cfg][f'{st * 1e3:g}mm'] = ent
    st2 = [r for r in rows if abs(r['sigma_t'] - 2e-3) < 1e-12]
    pooled = {key: _rms(r[key].get('err_con', np.nan) for r in st2)
              for key in ('observed', 'nonlinear', 'optimal')}
    worst_cfg = min(
        (table[c]['2mm']['constrained_reduction_optimal'], c) for c in table if '2mm' in table[c])
    worst_contact = min((table[c]['2mm']['constrained_reduction_optimal_at_contact'], c)
                        for c in table if '2mm' in table[c])
    # detection
    detection = {}
    for st in sorted({r['sigma_t'] for r in rows}):
        for sr in sorted({r['sigma_r'] for r in rows}):
            sel = [r for r in rows if r['sigma_t'] == st and r['sigma_r'] == sr]
            tp, fp, fn = (sum(r[k] for r in sel) for k in ('tp', 'fp', 'fn'))
            detection[f't{st * 1e3:g}mm_r{np.rad2deg(sr):g}deg'] = {
                'precision': tp / max(tp + fp, 1), 'recall': tp / max(tp + fn, 1),
                'corrected_with_detected_relation': float(np.mean(
                    [r['detected_corrected'] for r in sel]))}
    tp, fp, fn = (sum(r[k] for r in rows) for k in ('tp', 'fp', 'fn'))
    small = [r for r in rows if r['pairs'] <= 8]
    t_small = 1e3 * float(np.mean([r['pipeline_time'] for r in small]))
    c_small = 1e3 * float(np.mean([r['pipeline_cpu'] for r in small]))
    c_small_p95 = 1e3 * float(np.percentile([r['pipeline_cpu'] for r in small], 95))
    t_small_p95 = 1e3 * float(np.percentile([r['pipeline_time'] for r in small], 95))
    t_all = 1e3 * float(np.mean([r['pipeline_time'] for r in rows]))
    c_all = 1e3 * float(np.mean([r['pipeline_cpu'] for r in rows]))
    t_corr_small = 1e3 * float(np.mean([r['optimal']['time'] for r in small]))
    c_corr_small = 1e3 * float(np.mean([r['optimal']['cpu'] for r in small]))
    opt = by_method['optimal']
    goals = [
        goal('max_contact_residual_after_optimal_m', 1e-6, '<', opt['max_residual_m']),
        goal('max_contact_residual_after_nonlinear_m', 1e-6, '<',
             by_method['nonlinear']['max_residual_m']),
        goal('max_penetration_after_optimal_m (0 = numerically zero, <= 1e-9)', 1e-9, '<=',
             opt['max_penetration_m']),
        goal('max_penetration_after_nonlinear_m (<= 1e-9)', 1e-9, '<=',
             by_method['nonlinear']['max_penetration_m']),
        goal('max_free_translation_change_optimal_m', 1e-9, '<',
             opt['max_free_translation_change_m']),
        goal('frames_corrected_fraction_optimal', 1.0, '>=', opt['corrected'] / opt['frames']),
        goal('constrained_translation_error_reduction_at_2mm_pooled (rms obs / rms optimal)', 5.0,
             '>=', pooled['observed'] / max(pooled['optimal'], 1e-300)),
        goal('constrained_translation_error_reduction_at_2mm_worst_config_at_origin '
             f'({worst_cfg[1]})',
             5.0, '>=', worst_cfg[0]),
        goal('constrained_error_reduction_at_2mm_worst_config_at_contact_centroid '
             f'({worst_contact[1]})', 5.0, '>=', worst_contact[0]),
        goal('cpu_time_per_frame_ms_le8_pairs (detect + non-linear + optimal + penetration '
             'checks; thread CPU time)', 5.0, '<=', c_small),
        goal('wall_time_per_frame_ms_le8_pairs (same; wall clock on the shared machine)',
             5.0, '<=', t_small),
    ]
    write_report(
        'contact_correction', goals,
        quick=quick,
        settings={'sigma_t_m': SIGMA_T, 'sigma_r_rad': SIGMA_R,
                  'trials_per_pose_and_sigma': 4 if quick else 20,
                  'load_average_at_end': os.getloadavg(),
                  'noise': 'rotation R(w) left-multiplied (about the object origin), w ~ N(0, '
                           'sigma_r^2 I); translation + N(0, sigma_t^2 I) in the fixed frame',
                  'detection_tolerance': '3 sigma_t + 3 sigma_r * size / 2',
                  'penetration_test': 'winding number of vertices and edge samples every 2 mm'},
        configurations=per_config,
        by_method=by_method,
        constrained_rms_error_at_2mm_pooled_m=pooled,
        error_decomposition_rms=table,
        relation_detection={'overall': {'precision': tp / max(tp + fp, 1),
                                        'recall': tp / max(tp + fn, 1)}, **detection},
        timing_ms={'note': "wall = perf_counter; cpu = this thread's CPU time (what the frame "
                           'costs without preemption by other processes on the shared machine; '
                           'see settings.load_average_at_end)',
                   'pipeline_wall_mean_le8_pairs': t_small,
                   'pipeline_wall_p95_le8_pairs': t_small_p95,
                   'pipeline_cpu_mean_le8_pairs': c_small,
                   'pipeline_cpu_p95_le8_pairs': c_small_p95,
                   'pipeline_wall_mean_all': t_all, 'pipeline_cpu_mean_all': c_all,
                   'optimal_correction_only_wall_mean_le8_pairs': t_corr_small,
                   'optimal_correction_only_cpu_mean_le8_pairs': c_corr_small,
                   'detect_mean_all': 1e3 * float(np.mean([r['detect_time'] for r in rows]))},
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='one sigma pair, few trials')
    run(ap.parse_args().quick)


if __name__ == '__main__':
    main()
