"""Pure-core tests of ip_modeler: monomial order, incremental QR, fitting, bad input."""

from hypothesis import given, settings, strategies as st
from ip_modeler.evaluation import distance_to_zero_set, evaluate_model, zero_set_mesh
from ip_modeler.fitting import (
    check_point_cloud, estimate_normals, fit_3l_from_scratch, fit_gradient_one,
    fit_implicit_polynomial, fit_taubin, ImplicitPolynomialModel, normalize_points,
    three_layer_data)
from ip_modeler.incremental_qr import IncrementalQR
from ip_modeler.monomials import (degree_slice, evaluate_polynomial,
                                  evaluate_polynomial_gradient, evaluate_polynomial_on_grid,
                                  monomial_count, monomial_exponents, monomial_matrix,
                                  monomial_shift_indices)
from ip_modeler.shapes import sample_shape, visible_half
import numpy as np
import pytest

SIZE = 0.08


# ------------------------------------------------------------------------------- monomials
def test_graded_lex_order_matches_message_definition():
    E = monomial_exponents(2)
    assert [tuple(e) for e in E] == [
        (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1),
        (2, 0, 0), (1, 1, 0), (1, 0, 1), (0, 2, 0), (0, 1, 1), (0, 0, 2)]
    for n in range(9):
        E = monomial_exponents(n)
        assert len(E) == monomial_count(n) == (n + 1) * (n + 2) * (n + 3) // 6
        assert len({tuple(e) for e in E}) == len(E)
        # raising the degree only appends columns
        assert np.array_equal(monomial_exponents(n + 1)[:len(E)], E)
        tot = E.sum(axis=1)
        assert np.all(np.diff(tot) >= 0)
        for d in range(n + 1):
            block = [tuple(e) for e in E[degree_slice(d)]]
            assert all(sum(e) == d for e in block)
            assert block == sorted(block, reverse=True)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 6), st.integers(0, 2 ** 31 - 1))
def test_monomial_matrix_and_gradient_against_direct_formula(degree, seed):
    rng = np.random.default_rng(seed)
    X = rng.uniform(-1.2, 1.2, size=(7, 3))
    M = monomial_matrix(X, degree)
    E = monomial_exponents(degree)
    direct = np.prod(X[:, None, :] ** E[None, :, :], axis=2)
    np.testing.assert_allclose(M, direct, rtol=1e-12, atol=1e-12)
    a = rng.normal(size=len(E))
    np.testing.assert_allclose(evaluate_polynomial(a, X), direct @ a, rtol=1e-10, atol=1e-10)
    # gradient by central differences
    h = 1e-6
    g = evaluate_polynomial_gradient(a, X)
    for axis in range(3):
        dx = np.zeros(3)
        dx[axis] = h
        num = (evaluate_polynomial(a, X + dx) - evaluate_polynomial(a, X - dx)) / (2 * h)
        np.testing.assert_allclose(g[:, axis], num, rtol=1e-6, atol=1e-6)
    xs, ys, zs = np.linspace(-1, 1, 4), np.linspace(-0.5, 1, 3), np.linspace(0, 1, 5)
    grid = evaluate_polynomial_on_grid(a, xs, ys, zs)
    pts = np.stack(np.meshgrid(xs, ys, zs, indexing='ij'), axis=-1).reshape(-1, 3)
    np.testing.assert_allclose(grid.reshape(-1), evaluate_polynomial(a, pts), atol=1e-10)


# ---------------------------------------------------------------------------- incremental QR
def _fixed_signs(Q, R):
    s = np.sign(np.diag(R))
    s[s == 0] = 1
    return Q * s, R * s[:, None]


@pytest.mark.parametrize('variant', ['classical', 'modified', 'arnoldi'])
def test_incremental_qr_equals_from_scratch_qr(variant):
    rng = np.random.default_rng(3)
    X = rng.uniform(-1, 1, size=(400, 3))
    degree = 5
    M = monomial_matrix(X, degree)
    b = rng.normal(size=400)
    qr = IncrementalQR(b, variant=variant, points=X if variant == 'arnoldi' else None)
    for d in range(degree + 1):
        qr.append(M[:, degree_slice(d)])
        k = monomial_count(d)
        Q0, R0 = _fixed_signs(*np.linalg.qr(M[:, :k]))
        Q1, R1 = _fixed_signs(qr.Q, qr.R)
        assert qr.dropped == []
        np.testing.assert_allclose(Q1, Q0, rtol=0, atol=1e-10)
        np.testing.assert_allclose(R1, R0, rtol=0, atol=1e-10 * np.abs(R0).max())
        np.testing.assert_allclose(qr.Q.T @ qr.Q, np.eye(k), rtol=0, atol=1e-12)
        # back substitution of R a = Q^T b equals the least-squares solution (Eq. 22)
        ref = np.linalg.lstsq(M[:, :k], b, rcond=None)[0]
        np.testing.assert_allclose(qr.solve(), ref, rtol=1e-8, atol=1e-8)
        np.testing.assert_allclose(qr.residual_norm(), np.linalg.norm(M[:, :k] @ ref - b),
                                   rtol=1e-8)
    # any earlier degree can be solved again from the same factorisation
    ref2 = np.linalg.lstsq(M[:, :monomial_count(2)], b, rcond=None)[0]
    np.testing.assert_allclose(qr.solve(monomial_count(2)), ref2, rtol=1e-8, atol=1e-8)


def test_incremental_qr_drops_dependent_columns():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(50, 3))
    block = np.column_stack([A[:, 0] + A[:, 1], rng.normal(size=50), A[:, 2] * 2.0])
    qr = IncrementalQR(rng.normal(size=50))
    qr.append(A)
    mask = qr.append(block)
    assert mask.tolist() == [False, True, False]
    assert qr.dropped == [3, 5] and qr.rank == 4
    a = qr.solve()
    assert a[3] == 0.0 and a[5] == 0.0


def test_monomial_shift_indices_match_exponents():
    E = monomial_exponents(4)
    lowered, raised = monomial_shift_indices(4)
    unit = np.eye(3, dtype=np.int64)
    for c, e in enumerate(E):
        for axis in range(3):
            if e[axis] == 0:
                assert lowered[axis, c] == -1
            else:
                assert tuple(E[lowered[axis, c]]) == tuple(e - unit[axis])
            if e.sum() == 4:
                assert raised[axis, c] == -1
            else:
                assert tuple(E[raised[axis, c]]) == tuple(e + unit[axis])


def _three_layer_matrix(shape, n, degree, seed, half=True):
    P, N = sample_shape(shape, n, SIZE, np.random.default_rng(seed))
    if half:
        P, N = visible_half(P, N)
    X, b = three_layer_data(normalize_points(P)[0], N, 0.02)
    return X, b, monomial_matrix(X, degree)


def test_arnoldi_drops_the_columns_monomial_gram_schmidt_drops():
    """
    3L data of a sphere.

    x^2 + y^2 + z^2 is constant on each layer, so from degree 6 on the product of the three layers'
    equations vanishes on all points: exactly dependent columns.
    """
    X, b, M = _three_layer_matrix('sphere', 400, 7, 6, half=False)
    arnoldi = IncrementalQR(b, variant='arnoldi', points=X)
    classical = IncrementalQR(b, variant='classical')
    for d in range(8):
        arnoldi.append(M[:, degree_slice(d)])
        classical.append(M[:, degree_slice(d)])
    assert arnoldi.dropped == classical.dropped and len(arnoldi.dropped) >= 4
    assert min(arnoldi.dropped) >= monomial_count(5)
    a = arnoldi.solve(ridge=1e-6)
    assert np.all(a[arnoldi.dropped] == 0.0)
    np.testing.assert_allclose(a, classical.solve(ridge=1e-6), rtol=0,
                               atol=1e-9 * np.abs(a).max())
    # the unregularised fit is exact on the data, as the from-scratch solution is
    a0 = arnoldi.solve()
    ref = np.linalg.lstsq(M, b, rcond=None)[0]
    assert np.linalg.norm(M @ a0 - b) <= 1e-9 * np.linalg.norm(b)
    assert np.linalg.norm(M @ ref - b) <= 1e-9 * np.linalg.norm(b)


def test_arnoldi_second_pass_keeps_orthogonality():
    X, b, M = _three_layer_matrix('torus', 600, 10, 2)
    losses, passes = {}, {}
    for tol in (1e-10, 1e-15):
        qr = IncrementalQR(b, variant='arnoldi', points=X, orthogonality_tol=tol)
        for d in range(11):
            qr.append(M[:, degree_slice(d)])
        losses[tol] = np.abs(qr.Q.T @ qr.Q - np.eye(qr.rank)).max()
        passes[tol] = qr.reorthogonalised
    # the sketch asks for some second passes on this half view, and they hold the tolerance
    assert 0 < passes[1e-10] < passes[1e-15] and losses[1e-10] <= 1e-10
    assert losses[1e-15] <= 1e-13


def test_arnoldi_rejects_bad_setup():
    X = np.random.default_rng(0).uniform(-1, 1, size=(30, 3))
    M = monomial_matrix(X, 2)
    with pytest.raises(ValueError, match='points'):
        IncrementalQR(np.ones(30), variant='arnoldi')
    with pytest.raises(ValueError, match='shape'):
        IncrementalQR(np.ones(30), variant='arnoldi', points=X[:10])
    bad = X.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match='NaN'):
        IncrementalQR(np.ones(30), variant='arnoldi', points=bad)
    qr = IncrementalQR(np.ones(30), variant='arnoldi', points=X)
    with pytest.raises(ValueError, match='whole degrees'):
        qr.append(M[:, :3])
    qr.append(M[:, :4])
    with pytest.raises(ValueError, match='whole degrees'):
        qr.append(M[:, 4:7])


def test_incremental_qr_rejects_bad_blocks():
    qr = IncrementalQR(np.ones(10))
    with pytest.raises(ValueError, match='rows'):
        qr.append(np.ones((9, 2)))
    with pytest.raises(ValueError, match='NaN'):
        qr.append(np.full((10, 2), np.nan))
    with pytest.raises(ValueError, match='stabilization'):
        IncrementalQR(np.ones(3), stabilization='magic')


@pytest.mark.parametrize('variant', ['classical', 'arnoldi'])
def test_ridge_bounds_coefficients_on_ill_conditioned_case(variant):
    """Near-planar data: the z-columns are almost dependent; the plain solve explodes."""
    rng = np.random.default_rng(5)
    n = 300
    X = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n),
                         1e-7 * rng.normal(size=n)])
    M = monomial_matrix(X, 3)
    b = rng.normal(size=n)
    kw = {'variant': variant, 'points': X if variant == 'arnoldi' else None}
    plain = IncrementalQR(b, stabilization='none', **kw)
    ridge = IncrementalQR(b, stabilization='ridge', stability_tol=1e-4, **kw)
    dropped = IncrementalQR(b, stabilization='drop', stability_tol=1e-4, **kw)
    for q in (plain, ridge, dropped):
        for d in range(4):
            q.append(M[:, degree_slice(d)])
    a_plain, a_ridge, a_drop = plain.solve(), ridge.solve(), dropped.solve()
    assert len(ridge.unstable) > 0 and not plain.unstable
    assert np.abs(a_plain).max() > 1e5  # the unregularised solve is unstable
    assert np.abs(a_ridge).max() < 1e3  # ridge keeps the coefficients bounded
    assert np.abs(a_drop).max() < 1e3
    # and the fit quality on the data barely changes
    r_plain = np.linalg.norm(M @ a_plain - b)
    r_ridge = np.linalg.norm(M @ a_ridge - b)
    assert r_ridge <= 1.05 * r_plain
    # global ridge regression (all non-constant coefficients) bounds them as well
    a_global = plain.solve(ridge=1e-6)
    assert np.abs(a_global).max() < 1e3
    assert np.linalg.norm(M @ a_global - b) <= 1.05 * r_plain
    with pytest.raises(ValueError, match='ridge'):
        plain.solve(ridge=-1.0)


# ----------------------------------------------------------------------------------- fitting
def _sphere_through(points_centre, radius):
    """Coefficients of (x-c)^2 - r^2 in raw coordinates (degree 2, graded_lex)."""
    cx, cy, cz = points_centre
    return np.array([cx * cx + cy * cy + cz * cz - radius ** 2, -2 * cx, -2 * cy, -2 * cz,
                     1, 0, 0, 1, 0, 1])


def test_exact_recovery_of_known_polynomial_zero_set():
    """Samples of a known quartic (a torus): Taubin recovers it exactly, 3L to O(c^2)."""
    P, N = sample_shape('torus', 1500, SIZE, np.random.default_rng(6))
    R = 0.5 * SIZE / 1.3
    r = 0.3 * R
    Q, _ = sample_shape('torus', 500, SIZE, np.random.default_rng(7))  # fresh samples
    taubin = fit_taubin(P, 4)
    assert distance_to_zero_set(taubin, Q).max() < 1e-9 * SIZE
    # 3L targets +-c on the offset layers, which the torus quartic meets only to O(c^2):
    # the zero set converges to the torus quadratically as c shrinks
    errors = []
    for c in (0.01, 0.005, 0.0025):
        res = fit_implicit_polynomial(P, N, max_degree=6, target_rms=1e-3 * SIZE, offset=c,
                                      ridge=0.0)
        assert res.model.degree == 4
        d = distance_to_zero_set(res.model, Q)
        errors.append(np.sqrt(np.mean(d ** 2)))
    assert errors[-1] < 2e-5 * SIZE
    assert errors[0] / errors[-1] > 8.0  # ~16 for exact c^2 convergence
    # points of the fitted zero set satisfy the torus equation
    V, _ = zero_set_mesh(res.model, Q.min(0) - 0.01, Q.max(0) + 0.01, resolution=48)
    rho = np.sqrt(V[:, 0] ** 2 + V[:, 1] ** 2)
    tube = np.sqrt((rho - R) ** 2 + V[:, 2] ** 2)
    assert np.abs(tube - r).max() < 2e-3 * SIZE  # marching-cubes interpolation error


def test_sphere_polynomial_recovered_up_to_scale():
    rng = np.random.default_rng(8)
    c, radius = np.array([0.1, -0.2, 0.5]), 0.04
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    P = c + radius * u
    res = fit_implicit_polynomial(P, u, max_degree=4, target_rms=2e-5, offset=0.002)
    assert res.model.degree == 2
    # convert the normalised-coordinate polynomial to raw coordinates and compare
    Xs = P[:10] + rng.normal(scale=0.01, size=(10, 3))
    truth = evaluate_polynomial(_sphere_through(c, radius), Xs)
    fitted = res.model.value(Xs)
    ratio = fitted / truth
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-3)


def test_degree_rises_until_target_and_history_is_recorded():
    P, N = sample_shape('cube', 1500, SIZE, np.random.default_rng(9))
    res = fit_implicit_polynomial(P, N, max_degree=8, target_rms=0.01 * SIZE, patience=8)
    degrees = [s.degree for s in res.steps]
    assert degrees == list(range(1, res.model.degree + 1))
    assert res.steps[-1].rms_first_order <= 0.01 * SIZE
    assert all(s.rms_first_order > 0.01 * SIZE for s in res.steps[:-1])
    assert 4 <= res.model.degree <= 6
    ev = evaluate_model(res.model, P, N, SIZE)
    assert ev['rms_distance_rel'] <= 0.012
    assert ev['spurious_sheets'] == 0


def test_warm_start_skips_the_low_degree_sheet_checks_and_keeps_the_fit():
    # a half-visible cube (the live graph's case): the cold search checks every degree for
    # spurious sheets; started one below the cold fit's degree, the lower degrees are only
    # factorised, and the chosen model is the same (same factorisation, same ridge search)
    P, N = sample_shape('cube', 3000, SIZE, np.random.default_rng(9))
    P, N = visible_half(P, N)
    cold = fit_implicit_polynomial(P, N, max_degree=8, target_rms=0.01 * SIZE)
    d = cold.model.degree
    assert d >= 3
    warm = fit_implicit_polynomial(P, N, max_degree=8, target_rms=0.01 * SIZE,
                                   min_degree=d - 1)
    assert warm.model.degree == d
    np.testing.assert_allclose(warm.model.coefficients, cold.model.coefficients, atol=1e-9)
    assert all(s.spurious_sheets == -1 for s in warm.steps if s.degree < d - 1)
    assert all(s.spurious_sheets >= 0 for s in cold.steps)


def test_incremental_fit_equals_from_scratch_fit():
    P, N = sample_shape('superquadric', 800, SIZE, np.random.default_rng(10))
    res = fit_implicit_polynomial(P, N, max_degree=4, target_rms=0.0, patience=8, ridge=0.0)
    for solver in ('lstsq', 'householder'):
        ref = fit_3l_from_scratch(P, N, 4, solver=solver)
        np.testing.assert_allclose(res.models[4].coefficients, ref.coefficients, atol=1e-8)


def test_half_view_with_estimated_normals():
    P, N = sample_shape('sphere', 3000, SIZE, np.random.default_rng(11))
    P, N = visible_half(P, N)
    view = np.array([0.3, -0.4, 0.866]) * 10 * SIZE
    est = estimate_normals(P, viewpoint=view)
    assert np.mean(np.einsum('ij,ij->i', est, N)) > 0.99
    res = fit_implicit_polynomial(P, None, max_degree=4, target_rms=1e-3 * SIZE,
                                  viewpoint=view)
    assert res.model.degree == 2
    d = distance_to_zero_set(res.model, P)
    assert np.sqrt(np.mean(d ** 2)) < 1e-3 * SIZE


def test_baselines_fit_an_ellipsoid():
    P, N = sample_shape('ellipsoid', 1000, SIZE, np.random.default_rng(12))
    for model, tol in ((fit_taubin(P, 2), 1e-9), (fit_gradient_one(P, N, 2), 3e-3),
                       (fit_3l_from_scratch(P, N, 2, solver='householder'), 1e-3)):
        d = distance_to_zero_set(model, P)
        assert np.sqrt(np.mean(d ** 2)) < tol * SIZE, model.method


def test_normalisation_and_model_round_trip():
    P, _ = sample_shape('cylinder', 200, SIZE, np.random.default_rng(13))
    P = P + np.array([1.0, 2.0, 3.0])
    Pn, centre, scale = normalize_points(P)
    assert np.isclose(np.linalg.norm(Pn, axis=1).max(), 1.0)
    np.testing.assert_allclose(Pn * scale + centre, P)
    m = ImplicitPolynomialModel(1, [0.0, 1.0, 0.0, 0.0], centre, scale)
    np.testing.assert_allclose(m.denormalize(m.normalize(P)), P)
    # f = x_n, so the first-order distance is |x - cx| exactly, in metres
    np.testing.assert_allclose(m.first_order_distance(P), np.abs(P[:, 0] - centre[0]),
                               atol=1e-12)


# --------------------------------------------------------------------------------- bad input
def test_too_few_points_for_the_coefficients():
    P, N = sample_shape('sphere', 30, SIZE)
    with pytest.raises(ValueError, match='fewer than the 35 needed'):
        fit_3l_from_scratch(P, N, 4)
    with pytest.raises(ValueError, match='fewer than'):
        fit_implicit_polynomial(P[:3], N[:3], min_degree=1)


def test_adaptive_fit_stops_below_the_point_count():
    """30 points carry 90 3L rows: the adaptive fit stops where data run out, no crash."""
    P, N = sample_shape('sphere', 30, SIZE)
    res = fit_implicit_polynomial(P, N, max_degree=8, target_rms=1e-3 * SIZE)
    assert res.model.degree == 2


def test_planar_and_collinear_clouds_give_clear_errors():
    rng = np.random.default_rng(14)
    plane = np.column_stack([rng.uniform(size=100), rng.uniform(size=100), np.zeros(100)])
    with pytest.raises(ValueError, match='planar'):
        fit_implicit_polynomial(plane, np.tile([0, 0, 1.0], (100, 1)))
    line = np.outer(rng.uniform(size=100), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match='collinear'):
        fit_taubin(line, 2)
    with pytest.raises(ValueError, match='same point'):
        check_point_cloud(np.ones((10, 3)))


def test_nan_and_shape_errors():
    P, N = sample_shape('sphere', 100, SIZE)
    P[5, 1] = np.nan
    with pytest.raises(ValueError, match='1 non-finite'):
        fit_implicit_polynomial(P, N)
    with pytest.raises(ValueError, match=r'shape \(N, 3\)'):
        fit_implicit_polynomial(np.ones((10, 2)), None)
    P, N = sample_shape('sphere', 100, SIZE)
    N[3] = np.nan
    with pytest.raises(ValueError, match='normals'):
        fit_implicit_polynomial(P, N)
    with pytest.raises(ValueError, match='normals'):
        three_layer_data(P, N[:50], 0.02)
    with pytest.raises(ValueError, match='offset'):
        fit_implicit_polynomial(P, None, offset=0.0)
    with pytest.raises(ValueError, match='degree'):
        fit_implicit_polynomial(P, None, min_degree=3, max_degree=2)
