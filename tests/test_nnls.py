"""imupipe's small NNLS (every active set at once) against scipy's Lawson-Hanson NNLS."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls as scipy_nnls

from imupipe.stages.allan.nnls import MAX_UNKNOWNS, nnls


def _cost(a: np.ndarray, b: np.ndarray, x: np.ndarray) -> float:
    return float(np.sum((a @ x - b) ** 2))


@pytest.mark.parametrize("p", range(1, MAX_UNKNOWNS + 1))
def test_the_solution_is_scipys(p):
    """Columns of scales 1e-4..1e4 (as the Allan fit's before scaling), right-hand sides of
    either sign: the same x, to the accuracy of the problem, and never a larger residual."""
    rng = np.random.default_rng(p)
    active = 0
    for _ in range(60):
        a = rng.random((21, p)) * np.exp(rng.normal(0.0, 2.0, p))
        b = rng.standard_normal(21) + a @ rng.normal(0.0, 1.0, p)
        want = scipy_nnls(a, b)[0]
        got = nnls(a, b)
        assert (got >= 0.0).all()
        assert _cost(a, b, got) <= _cost(a, b, want) * (1 + 1e-12) + 1e-300
        scale = np.linalg.norm(b) / np.linalg.norm(a, axis=0)  # the size x can have
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * scale.max())
        active += int(np.count_nonzero(want))
    assert 0 < active < 60 * p  # some constraints bind, some do not


def test_the_allan_fits_problems_against_scipy():
    """The log-space problems of the Allan fit (every subset of the terms, profile solves):
    each Gauss-Newton step's NNLS as scipy solves it."""
    from test_allan_run_speed import _fit_problems

    from imupipe.stages.allan import fit

    count = 0
    for problem, terms, _, _ in _fit_problems():
        s = problem.scaled(terms)
        u = np.ones(len(terms))
        mu = s.a_s @ u
        jac = s.a_s / mu[:, None]
        a, b = s.sw_col * jac, s.sw * (jac @ u - (np.log(mu) - s.target))
        np.testing.assert_allclose(nnls(a, b), scipy_nnls(a, b)[0], rtol=1e-9, atol=1e-12)
        first_a = s.sw_col * s.rel * s.scale
        np.testing.assert_allclose(
            nnls(first_a, s.sw), scipy_nnls(first_a, s.sw)[0], rtol=1e-9, atol=1e-12
        )
        count += 1
    assert count > 250
    assert fit.nnls is nnls


def test_zero_is_the_answer_when_every_column_points_away():
    a = np.abs(np.random.default_rng(0).random((10, 3))) + 0.1
    np.testing.assert_array_equal(nnls(a, -np.ones(10)), np.zeros(3))


def test_dependent_columns_still_give_a_least_residual_solution():
    a = np.ones((8, 2))  # two equal columns: many solutions, one residual
    b = np.full(8, 2.0)
    x = nnls(a, b)
    assert (x >= 0).all()
    assert _cost(a, b, x) == pytest.approx(0.0, abs=1e-20)


def test_more_unknowns_than_it_solves_is_refused():
    with pytest.raises(ValueError, match="1 to 6 unknowns"):
        nnls(np.ones((10, 7)), np.ones(10))
