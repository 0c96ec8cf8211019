#!/usr/bin/env python3
"""
Benchmark of ip_modeler (issue 7): adaptive-degree 3L fits by incremental QR vs baselines.

Cases: sphere, ellipsoid, cube (0.08 m), cylinder, torus and a superquadric (|x|^3+|y|^3+|z|^3),
all 0.08 m across, sampled analytically with exact outward normals; Gaussian noise sigma in
{0, 0.5, 1, 2} % of the size per coordinate; full view and half view (points whose normal faces
a viewer). Noise-free cases use the exact normals; noisy cases use PCA normals estimated from
the noisy points (16 neighbours), their sign taken from the sensor side (emulated by the true
normal's sign).

Per case: the adaptive fit (target RMS first-order distance sqrt((1 % of size)^2 + sigma^2),
degrees 1..8), evaluated against the noise-free points: true RMS/max distance to the zero set,
normal agreement, spurious sheets inside the data's bounding region, time; Taubin and
gradient-one at the same degree, evaluated the same way. Noise-free cases also evaluate every
degree 1..8.
The fitter's spurious-sheet check (raise the ridge while its zero set has a piece far from the
input) is on; noise-free cases also report every degree without it, for comparison.
Timing: the incremental fit through degrees 1..8 (append + back substitution per degree; the
fitter's default variant 'arnoldi', and the monomial BCGS2/BMGS2 variants for reference) vs
from-scratch Householder QR (numpy.linalg.qr + back substitution) and numpy.linalg.lstsq per
degree, on the same 3L matrices, interleaved repetitions, at 1000, 3000 and 10000 points.

BLAS runs single-threaded (OPENBLAS_NUM_THREADS=1 unless set): the 2 cores are shared with
other jobs, and multi-threaded BLAS timings under contention were 3-6x slower and erratic.

Run: python bench/ip_fitting.py [--quick]   (writes bench/results/ip_fitting.json)
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from typing import Dict, List

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy is imported

from ip_modeler.evaluation import evaluate_model  # noqa: E402
from ip_modeler.fitting import (DEFAULT_3L_OFFSET, estimate_normals,  # noqa: E402
                                fit_gradient_one, fit_implicit_polynomial, fit_taubin,
                                normalize_points, three_layer_data)
from ip_modeler.incremental_qr import IncrementalQR  # noqa: E402
from ip_modeler.monomials import degree_slice, monomial_count, monomial_matrix  # noqa: E402
from ip_modeler.shapes import add_noise, sample_shape, SHAPES, visible_half  # noqa: E402
import numpy as np  # noqa: E402
from scipy.linalg import solve_triangular  # noqa: E402
from stereo_manip_tools.bench_report import goal, write_report  # noqa: E402

SIZE = 0.08
NOISE = (0.0, 0.005, 0.01, 0.02)
VIEWS = ('full', 'half')
MAX_DEGREE = 8
N_POINTS = 2000


def _case_data(shape: str, noise: float, view: str, seed: int):
    rng = np.random.default_rng(seed)
    P, N = sample_shape(shape, N_POINTS if view == 'full' else 2 * N_POINTS, SIZE, rng)
    if view == 'half':
        P, N = visible_half(P, N)
    if noise == 0.0:
        return P, N, P, N
    Pn = add_noise(P, noise * SIZE, rng)
    est = estimate_normals(Pn, k=16)
    est *= np.where(np.einsum('ij,ij->i', est, N) < 0, -1.0, 1.0)[:, None]
    return Pn, est, P, N


def run_cases(quick: bool) -> List[Dict]:
    shapes = list(SHAPES)
    noises = NOISE if not quick else (0.0, 0.02)
    rows = []
    for si, shape in enumerate(shapes):
        for noise in noises:
            for view in VIEWS:
                seed = 1000 * si + int(noise * 1000) + (7 if view == 'half' else 0)
                P, normals, P_ref, N_ref = _case_data(shape, noise, view, seed)
                target = float(np.hypot(0.01, noise)) * SIZE
                t0 = time.perf_counter()
                res = fit_implicit_polynomial(P, normals, max_degree=MAX_DEGREE,
                                              target_rms=target)
                t_fit = time.perf_counter() - t0
                ev = evaluate_model(res.model, P_ref, N_ref, SIZE)
                row = {
                    'shape': shape, 'noise': noise, 'view': view, 'points': int(len(P)),
                    'target_rms': target, 'degree': res.model.degree,
                    'stop_reason': res.stop_reason, 'fit_seconds': t_fit,
                    'rms_first_order_per_degree': [s.rms_first_order for s in res.steps],
                    'dropped_columns': sum(s.dropped for s in res.steps),
                    'ridge_used': res.steps[-1].ridge if res.steps else None,
                    '3L': ev,
                }
                deg = res.model.degree
                for name, fitter in (('taubin', lambda: fit_taubin(P, deg)),
                                     ('gradient_one', lambda: fit_gradient_one(P, normals, deg))):
                    t0 = time.perf_counter()
                    model = fitter()
                    dt = time.perf_counter() - t0
                    row[name] = evaluate_model(model, P_ref, N_ref, SIZE)
                    row[name]['fit_seconds'] = dt
                if noise == 0.0:
                    full = fit_implicit_polynomial(P, normals, max_degree=MAX_DEGREE,
                                                   target_rms=0.0, patience=MAX_DEGREE)
                    per = {}
                    for d, m in sorted(full.models.items()):
                        e = evaluate_model(m, P_ref, N_ref, SIZE)
                        per[d] = {'rms_distance_rel': e['rms_distance_rel'],
                                  'max_distance_rel': e['max_distance_rel'],
                                  'spurious_sheets': e['spurious_sheets'],
                                  'far_area_fraction': e['far_area_fraction']}
                    row['per_degree'] = per
                    row['ridge_per_degree'] = {s.degree: s.ridge for s in full.steps}
                    # the same fits without the fitter's spurious-sheet check (plain ridge 1e-6)
                    plain = fit_implicit_polynomial(P, normals, max_degree=MAX_DEGREE,
                                                    target_rms=0.0, patience=MAX_DEGREE,
                                                    sheet_check=False)
                    row['per_degree_without_sheet_check'] = {
                        d: {k: v for k, v in evaluate_model(m, P_ref, N_ref, SIZE).items()
                            if k in ('rms_distance_rel', 'spurious_sheets')}
                        for d, m in sorted(plain.models.items())}
                rows.append(row)
                print(f'{shape:12s} noise {noise:5.3f} {view:4s}: degree {deg} '
                      f"RMS {ev['rms_distance_rel']:.4f} max {ev['max_distance_rel']:.4f} "
                      f"sheets {ev['spurious_sheets']} | Taubin "
                      f"{row['taubin']['rms_distance_rel']:.4f} grad1 "
                      f"{row['gradient_one']['rms_distance_rel']:.4f} | {t_fit:.3f} s",
                      flush=True)
    return rows


def _incremental(M, b, X, variant='arnoldi'):
    """Run the adaptive fit's factorisation: append each degree block, solve, degrees 1..8."""
    qr = IncrementalQR(b, capacity=M.shape[1], variant=variant,
                       points=X if variant == 'arnoldi' else None)
    out = []
    for d in range(1, MAX_DEGREE + 1):
        qr.append(M[:, :4] if d == 1 else M[:, degree_slice(d)])
        out.append(qr.solve())
    return out, qr


def _householder(M, b, X=None):
    out = []
    for d in range(1, MAX_DEGREE + 1):
        Q, R = np.linalg.qr(M[:, :monomial_count(d)])
        out.append(solve_triangular(R, Q.T @ b))
    return out


def _lstsq(M, b, X=None):
    return [np.linalg.lstsq(M[:, :monomial_count(d)], b, rcond=None)[0]
            for d in range(1, MAX_DEGREE + 1)]


def _per_degree_times(M, b, X, reps):
    inc = np.zeros((reps, MAX_DEGREE))
    hh = np.zeros((reps, MAX_DEGREE))
    for r in range(reps):
        qr = IncrementalQR(b, capacity=M.shape[1], variant='arnoldi', points=X)
        for d in range(1, MAX_DEGREE + 1):
            t0 = time.perf_counter()
            qr.append(M[:, :4] if d == 1 else M[:, degree_slice(d)])
            qr.solve()
            inc[r, d - 1] = time.perf_counter() - t0
            t0 = time.perf_counter()
            Q, R = np.linalg.qr(M[:, :monomial_count(d)])
            solve_triangular(R, Q.T @ b)
            hh[r, d - 1] = time.perf_counter() - t0
    return inc.min(axis=0).tolist(), hh.min(axis=0).tolist()


def run_timing(quick: bool) -> Dict:
    sizes = (1000, 3000, 10000) if not quick else (1000, 3000)
    out = {'load_average_before': list(os.getloadavg())}
    for n in sizes:
        reps = (25 if n <= 3000 else 7) if not quick else 5
        P, N = sample_shape('superquadric', n, SIZE, np.random.default_rng(n))
        Pn, _, _ = normalize_points(P)
        X, b = three_layer_data(Pn, N, DEFAULT_3L_OFFSET)
        M = monomial_matrix(X, MAX_DEGREE)
        # same answer from all of them (sanity check of the timed code)
        (sol_inc, qr_inc), sol_cls = _incremental(M, b, X), _incremental(M, b, X, 'classical')[0]
        a_ls = _lstsq(M, b)[-1]
        agree = float(max(np.abs(sol_inc[-1] - a_ls).max(), np.abs(sol_cls[-1] - a_ls).max(),
                          np.abs(_householder(M, b)[-1] - a_ls).max()) / np.abs(a_ls).max())
        loss = float(np.abs(qr_inc.Q.T @ qr_inc.Q - np.eye(qr_inc.rank)).max())
        resid = [float(np.linalg.norm(M @ a - b)) for a in (sol_inc[-1], a_ls)]
        times = {'incremental': [], 'incremental_classical_bcgs2': [],
                 'incremental_modified_bmgs2': [], 'householder': [], 'lstsq': []}
        fns = {'incremental': lambda M, b, X: _incremental(M, b, X),
               'incremental_classical_bcgs2': lambda M, b, X: _incremental(M, b, X, 'classical'),
               'incremental_modified_bmgs2': lambda M, b, X: _incremental(M, b, X, 'modified'),
               'householder': _householder, 'lstsq': _lstsq}
        for _ in range(reps):
            for name, fn in fns.items():
                t0 = time.perf_counter()
                fn(M, b, X)
                times[name].append(time.perf_counter() - t0)
        best = {k: float(np.min(v)) for k, v in times.items()}
        median = {k: float(np.median(v)) for k, v in times.items()}
        inc_deg, hh_deg = _per_degree_times(M, b, X, max(3, reps // 3))
        out[str(n)] = {
            'rows': int(M.shape[0]), 'columns': int(M.shape[1]),
            'best_seconds': best, 'median_seconds': median,
            'speedup_vs_householder_best': best['householder'] / best['incremental'],
            'speedup_vs_lstsq_best': best['lstsq'] / best['incremental'],
            'speedup_vs_householder_median': median['householder'] / median['incremental'],
            'speedup_vs_lstsq_median': median['lstsq'] / median['incremental'],
            'classical_bcgs2_speedup_vs_lstsq_best':
                best['lstsq'] / best['incremental_classical_bcgs2'],
            'per_degree_best_seconds': {'incremental': inc_deg, 'householder': hh_deg},
            'max_coefficient_difference_rel_to_lstsq': agree,
            'incremental_orthogonality_loss_max_abs_QtQ_minus_I': loss,
            'incremental_second_pass_columns': int(qr_inc.reorthogonalised),
            'residual_norm_incremental_vs_lstsq': resid,
        }
        o = out[str(n)]
        print(f'timing {n} points ({M.shape[0]}x{M.shape[1]}): incremental (arnoldi) '
              f"{best['incremental'] * 1e3:.1f} ms, Householder {best['householder'] * 1e3:.1f}"
              f" ms ({o['speedup_vs_householder_best']:.2f}x), lstsq "
              f"{best['lstsq'] * 1e3:.1f} ms ({o['speedup_vs_lstsq_best']:.2f}x), classical "
              f"BCGS2 {best['incremental_classical_bcgs2'] * 1e3:.1f} ms, modified BMGS2 "
              f"{best['incremental_modified_bmgs2'] * 1e3:.1f} ms; loss of orthogonality "
              f'{loss:.1e}', flush=True)
    out['load_average_after'] = list(os.getloadavg())
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.strip().splitlines()[0])
    parser.add_argument('--quick', action='store_true', help='fewer cases and repetitions')
    args = parser.parse_args()
    t_start = time.perf_counter()
    rows = run_cases(args.quick)
    timing = run_timing(args.quick)

    def find(shape, noise, view):
        return next(r for r in rows if r['shape'] == shape and r['noise'] == noise
                    and r['view'] == view)

    goals = []
    for view in VIEWS:
        goals.append(goal(f'sphere_noise0_{view}_selected_degree', 2, '==',
                          find('sphere', 0.0, view)['degree']))
        goals.append(goal(f'torus_noise0_{view}_selected_degree', 4, '==',
                          find('torus', 0.0, view)['degree']))
    cube = find('cube', 0.0, 'full')
    goals.append(goal('cube_noise0_full_selected_degree', 6, '<=', cube['degree']))
    goals.append(goal('cube_noise0_full_rms_distance_rel', 0.01, '<=',
                      cube['3L']['rms_distance_rel']))
    sheets = [(r['shape'], r['view'], d, v['spurious_sheets']) for r in rows
              if r['noise'] == 0.0 for d, v in r['per_degree'].items()]
    goals.append(goal('spurious_sheets_noise0_all_shapes_views_degrees_1_to_8', 0, '==',
                      sum(s[3] for s in sheets)))
    goals.append(goal('spurious_sheets_noise0_full_views_degrees_1_to_8', 0, '==',
                      sum(s[3] for s in sheets if s[1] == 'full')))
    unchecked = [(r['shape'], r['view'], d, v['spurious_sheets']) for r in rows
                 if r['noise'] == 0.0 for d, v in r['per_degree_without_sheet_check'].items()]
    goals.append(goal('spurious_sheets_noise0_adaptive_fits', 0, '==',
                      sum(r['3L']['spurious_sheets'] for r in rows if r['noise'] == 0.0)))
    sizes_timing = [t for k, t in timing.items() if not k.startswith('load')]
    goals.append(goal('incremental_speedup_vs_householder_min_over_sizes', 1.8, '>=',
                      min(t['speedup_vs_householder_best'] for t in sizes_timing)))
    goals.append(goal('incremental_speedup_vs_lstsq_min_over_sizes', 3.0, '>=',
                      min(t['speedup_vs_lstsq_best'] for t in sizes_timing)))
    noisy = [r for r in rows if r['noise'] > 0]
    worse_taubin = [f"{r['shape']}/{r['noise']}/{r['view']}" for r in noisy
                    if r['3L']['rms_distance'] >= r['taubin']['rms_distance']]
    worse_g1 = [f"{r['shape']}/{r['noise']}/{r['view']}" for r in noisy
                if r['3L']['rms_distance'] >= r['gradient_one']['rms_distance']]
    goals.append(goal('noisy_cases_3L_rms_not_below_taubin', 0, '==', len(worse_taubin)))
    goals.append(goal('noisy_cases_3L_rms_not_below_gradient_one', 0, '==', len(worse_g1)))
    summary = [{k: r[k] for k in ('shape', 'noise', 'view', 'points', 'degree', 'fit_seconds')}
               | {'rms_distance_rel': r['3L']['rms_distance_rel'],
                  'max_distance_rel': r['3L']['max_distance_rel'],
                  'spurious_sheets': r['3L']['spurious_sheets'],
                  'mean_abs_cos': r['3L']['mean_abs_cos'],
                  'taubin_rms_distance_rel': r['taubin']['rms_distance_rel'],
                  'gradient_one_rms_distance_rel': r['gradient_one']['rms_distance_rel']}
               for r in rows]
    write_report(
        'ip_fitting', goals,
        quick=args.quick,
        size_m=SIZE, noise_levels=list(NOISE), views=list(VIEWS), max_degree=MAX_DEGREE,
        points_full_view=N_POINTS,
        target_rule='target RMS first-order distance = sqrt((0.01 * size)^2 + sigma^2)',
        spurious_sheet_rule=('connected piece of the marching-cubes zero set (64 cells along '
                             'the longest side) inside the data bounding box grown 10 %, never '
                             'within 10 % of the size of a data point'),
        timing_rule=('best of interleaved repetitions; incremental = append each degree block '
                     'and back-substitute, degrees 1..8, variant arnoldi (the fitter default; '
                     'classical BCGS2 and modified BMGS2 on the monomials timed beside it); '
                     'baselines from scratch per degree on the same 3L matrix; 2 cores shared '
                     'with other jobs (see load averages)'),
        cases_where_3L_not_below_taubin=worse_taubin,
        cases_where_3L_not_below_gradient_one=worse_g1,
        noise_free_spurious_sheets=[s for s in sheets if s[3]],
        noise_free_spurious_sheets_without_sheet_check=[s for s in unchecked if s[3]],
        sheet_check_rule=('the fitter checks each degree for spurious sheets on its own input '
                          '(same rule, 64-sample grid) and raises the ridge by sqrt(10) up to '
                          '1e-4 while any remain; in noise-free cases the input equals the '
                          'reference points, so the evaluation repeats that check at finer '
                          'resolution; per_degree_without_sheet_check gives the plain fits'),
        summary=summary, cases=rows, timing=timing,
        python=platform.python_version(), numpy=np.__version__,
        openblas_num_threads=os.environ.get('OPENBLAS_NUM_THREADS'),
        wall_seconds=time.perf_counter() - t_start,
    )


if __name__ == '__main__':
    main()
