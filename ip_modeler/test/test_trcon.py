"""
The dtrcon fallback (SciPy < 1.12) returns LAPACK's estimate.

Equal to scipy's dtrcon where this SciPy has it, and within [exact, n * exact] of the exact
reciprocal condition number.
"""

from ip_modeler.trcon import dtrcon
import numpy as np
import pytest


def exact_rcond(t: np.ndarray, norm: str) -> float:
    order = 1 if norm == '1' else np.inf
    return 1.0 / (np.linalg.norm(t, order) * np.linalg.norm(np.linalg.inv(t), order))


def triangulars(seed: int):
    rng = np.random.default_rng(seed)
    for n in (1, 2, 3, 5, 8, 13, 30):
        for scale in (1.0, 1e-3, 1e3):
            a = rng.normal(size=(n, n)) * scale
            a[np.diag_indices(n)] += np.sign(rng.normal(size=n)) * rng.uniform(0.01, 3, n)
            yield a
        # graded (ill-conditioned) upper triangle, as R factors of monomial columns are
        g = np.triu(rng.normal(size=(n, n))) * np.logspace(0, -8, n)[None, :]
        g[np.diag_indices(n)] = np.logspace(0, -8, n)
        yield g


@pytest.mark.parametrize('norm', ['1', 'I'])
@pytest.mark.parametrize('uplo', ['U', 'L'])
def test_estimate_bounds_the_exact_value(norm, uplo):
    for a in triangulars(1):
        t = np.triu(a) if uplo == 'U' else np.tril(a)
        rcond, info = dtrcon(a, norm=norm, uplo=uplo)
        exact = exact_rcond(t, norm)
        assert info == 0
        # the estimate of ||inv(T)|| is a lower bound, within a factor n of the truth
        assert exact * (1 - 1e-9) <= rcond <= exact * len(a) * (1 + 1e-9)


@pytest.mark.parametrize('norm', ['1', 'I'])
@pytest.mark.parametrize('uplo', ['U', 'L'])
@pytest.mark.parametrize('diag', ['N', 'U'])
def test_same_estimate_as_lapack(norm, uplo, diag):
    lapack = pytest.importorskip('scipy.linalg.lapack')
    if not hasattr(lapack, 'dtrcon'):
        pytest.skip('this SciPy has no scipy.linalg.lapack.dtrcon (< 1.12) to compare with')
    for a in triangulars(2):
        ours, _ = dtrcon(a, norm=norm, uplo=uplo, diag=diag)
        theirs, info = lapack.dtrcon(np.asfortranarray(a), norm=norm, uplo=uplo, diag=diag)
        assert info == 0
        assert ours == pytest.approx(theirs, rel=1e-9)


def test_singular_and_empty():
    assert dtrcon(np.triu(np.ones((3, 3))) - np.diag([0, 1, 1]))[0] == 0.0
    assert dtrcon(np.zeros((0, 0)))[0] == 1.0
    with pytest.raises(ValueError):
        dtrcon(np.ones((2, 3)))
