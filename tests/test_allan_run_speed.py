"""Issue 17, item 2: what keeps an Allan run fast without changing its results. The deviations'
sums of squares go through BLAS dots of at most ``DOT`` points (single-threaded in OpenBLAS);
a quiet run that writes no corrected MCAP imports neither rich (the progress bar) nor the MCAP
writer. The stage's fast paths against the straightforward computations they replace: the
deviations axis by axis (the same sums, bit for bit), every row's dots in one call, the noise
identification in reused memory with its autocorrelations from sums (the same alphas), the fit's
Gauss-Newton with each cost evaluated once (the same coefficients, bit for bit; its NNLS against
scipy's in ``test_nnls.py``), the motion check's blocks by bisection. The times themselves:
``benchmarks/bench_allan.py``."""

from __future__ import annotations

import itertools
import subprocess
import sys

import numpy as np
import pytest

from imupipe.pipeline.simulate import simulate, write_log
from imupipe.stages.allan import estimators as est


@pytest.mark.parametrize("n", [1, 7, est.DOT - 1, est.DOT, est.DOT + 1, 3 * est.DOT + 5])
def test_dot_in_pieces_is_the_sum_of_products(n):
    rng = np.random.default_rng(n)
    a, b = rng.standard_normal(n), rng.standard_normal(n)
    assert est._dot(a, b) == pytest.approx(float(np.sum(a * b)), rel=1e-12, abs=1e-12)


def test_sumsq_lagged_matches_the_direct_second_difference():
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.standard_normal((2, 3 * est.CHUNK + 17)), axis=1)
    for m in (1, 3, 64, est.CHUNK // 2, est.CHUNK // 2 + 1, est.CHUNK + 5):
        count = x.shape[1] - 2 * m
        d = x[:, 2 * m :] - 2.0 * x[:, m:-m] + x[:, : -2 * m]
        np.testing.assert_allclose(
            est._sumsq_lagged(x, m, False, count), np.sum(d * d, axis=1), rtol=1e-11
        )


def test_quiet_allan_run_imports_no_progress_bar_nor_mcap_writer_nor_arrow_compute(tmp_path):
    """Nor ``pyarrow.compute``, whose import (its functions' docs parsed) costs 0.06-0.09 s
    CPU: a CSV read with a numeric time column does not need it (issue 39)."""
    table, _ = simulate("static", {"duration_s": 60.0, "rate_hz": 100.0, "temperature": None}, 2)
    write_log(tmp_path / "static.csv", table)
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(
        '[inputs.static]\npath = "static.csv"\n\n[[stages]]\ntype = "allan"\n\n'
        '[output]\ndir = "out"\nreport = false\n'
    )
    code = (
        "import sys\n"
        "from imupipe.pipeline.run import run\n"
        f"run({str(cfg)!r}, quiet=True)\n"
        "mods = ('rich', 'imupipe.pipeline.writers.mcap', 'pyarrow.compute')\n"
        "print(sorted(m for m in mods if m in sys.modules))\n"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip().splitlines()[-1] == "[]"
    assert (tmp_path / "out" / "imu.yaml").exists()


# -- the stage's fast paths against the straightforward computations they replace ----------------
def _straight_deviation(x, tau0, kind, m):
    """Every factor over all axes at once, factor by factor (the order before)."""
    ext = est._reflect(x) if kind == "totdev" else None
    return np.array([np.sqrt(est._variance_at(kind, x, int(mi), tau0, ext)[0]) for mi in m])


@pytest.mark.parametrize("kind", est.KINDS)
def test_deviation_axis_by_axis_is_factor_by_factor(kind):
    rng = np.random.default_rng(5)
    n = est.CHUNK + 4001  # two chunks
    y = rng.standard_normal((n, 3)) + np.cumsum(rng.standard_normal((n, 3)), axis=0) * 1e-3
    x = est.rate_to_phase(y, 0.01)
    m = est.tau_grid("log", est.max_af(kind, x.shape[1]), 5)
    dev = est.deviation_of_phase(x, 0.01, kind, m)
    np.testing.assert_array_equal(dev.dev, _straight_deviation(x, 0.01, kind, dev.m))


@pytest.mark.parametrize("kind", ["oadev", "totdev"])
def test_axes_on_threads_are_the_axes_in_turn(monkeypatch, kind):
    """Phase and deviation with each axis on a thread of its own (two, whatever this machine
    has) are the serial results, bit for bit."""
    rng = np.random.default_rng(6)
    y = rng.standard_normal((est.CHUNK + 999, 4)) + [0.1, -2.0, 3.0, 0.0]
    m = est.tau_grid("log", est.max_af(kind, len(y) + 1), 5)
    threads = set()
    pool_map = est.ThreadPoolExecutor.map

    def spy(pool, fn, *its):
        threads.add(pool._max_workers)
        return pool_map(pool, fn, *its)

    monkeypatch.setattr(est.ThreadPoolExecutor, "map", spy)
    monkeypatch.setattr(est, "PARALLEL_POINTS", 1 << 40)
    x = est.rate_to_phase(y, 0.01)
    dev = est.deviation_of_phase(x, 0.01, kind, m)
    assert not threads
    monkeypatch.setattr(est, "PARALLEL_POINTS", 1)
    monkeypatch.setattr(est, "usable_cores", lambda: 2)
    x2 = est.rate_to_phase(y, 0.01)
    dev2 = est.deviation_of_phase(x2, 0.01, kind, m)
    assert threads == {2}
    np.testing.assert_array_equal(x2, x)
    np.testing.assert_array_equal(dev2.dev, dev.dev)
    np.testing.assert_array_equal(dev2.n, dev.n)


@pytest.mark.parametrize("n", [2, 30, est.DOT - 1, est.DOT, est.DOT + 1, 3 * est.DOT + 5])
def test_row_dots_are_the_dots_of_each_row(n):
    rng = np.random.default_rng(n)
    a = rng.standard_normal((6, n + 7))[:, :n]  # rows of a wider array, as in the noise work
    b = rng.standard_normal((6, n))
    p = rng.standard_normal(n)
    for got, want in (
        (est._row_dots(a, b), [est._dot(r, s) for r, s in zip(a, b, strict=True)]),
        (est._row_dots(a, p), [est._dot(r, p) for r in a]),
        (est._row_dots(a[:, :-1], a[:, 1:]), [est._dot(r[:-1], r[1:]) for r in a]),
    ):
        np.testing.assert_array_equal(got, np.array(want, dtype=np.float64))


def test_dot_is_the_sum_of_its_pieces_in_order():
    rng = np.random.default_rng(3)
    for n in (est.DOT + 1, 5 * est.DOT, 7 * est.DOT + 11):
        a, b = rng.standard_normal(n), rng.standard_normal(n)
        pieces = sum(np.dot(a[i : i + est.DOT], b[i : i + est.DOT]) for i in range(0, n, est.DOT))
        assert est._dot(a, b) == float(pieces)


def _straight_noise_alpha(x, m, dmax=2):
    """The lag-1 identification as written before: the decimated points copied, detrended and
    differenced row by row, each autocorrelation from a mean-removed copy."""
    z = np.array(x[:, : m * est.NOISE_ID_MAX_POINTS : m], dtype=np.float64)
    if (x.shape[1] + m - 1) // m < 30:
        return None
    t = np.linspace(-1.0, 1.0, z.shape[1])
    t2 = t * t
    t2 -= t2.mean()
    z -= z.mean(axis=1, keepdims=True)
    for p in (t, t2):
        for row in z:
            row -= (est._dot(row, p) / est._dot(p, p)) * p
    alpha, todo = np.zeros(len(x), dtype=np.int64), np.arange(len(x))
    for d in range(dmax + 1):
        c = z - z.mean(axis=1, keepdims=True)
        r1 = np.array([est._dot(r[:-1], r[1:]) / est._dot(r, r) for r in c])
        delta = r1 / (1.0 + r1)
        done = (delta < 0.25) | (d >= dmax) | (z.shape[1] < 4)
        alpha[todo[done]] = -np.round(2.0 * delta[done]).astype(np.int64) - 2 * d + 2
        todo = todo[~done]
        if not len(todo):
            break
        z = np.diff(z[~done], axis=1)
    return alpha


def _power_law(rng, alpha, n):
    """Rate noise with PSD ~ f^alpha."""
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    shape = f ** (alpha / 2.0) * (rng.standard_normal(len(f)) + 1j * rng.standard_normal(len(f)))
    return np.fft.irfft(shape, n)


@pytest.mark.parametrize("n", [3000, 200_001, 600_001])
def test_noise_identification_is_the_straightforward_one(n):
    """Every power law alpha = 2 .. -2 and an IMU-like mix (white + random walk), at every
    factor of the auto grid's octaves and of a dense log grid, with Allan (dmax 2) and
    Hadamard (dmax 3) differencing: the same alphas as the copy-and-loop computation; and the
    autocorrelation from sums agrees with the mean-removed copy's to rounding."""
    rng = np.random.default_rng(n)
    cols = [_power_law(rng, a, n) for a in (2, 1, 0, -1, -2)]
    cols.append(rng.standard_normal(n) + 0.01 * np.cumsum(rng.standard_normal(n)))
    x = est.rate_to_phase(cols, 0.0025)
    top = est.max_af("oadev", x.shape[1])
    work = est.NoiseWork.of(x)
    for m in np.union1d(est.tau_grid("octave", top), est.tau_grid("log", top, 20)):
        for dmax in (2, 3):
            want = _straight_noise_alpha(x, int(m), dmax)
            got = est.noise_alpha(x, int(m), dmax, work)
            assert (want is None and got is None) or np.array_equal(got, want), (m, dmax)
    z = np.ascontiguousarray(x[:, :: max(1, x.shape[1] // 5000)])
    est._detrend2(z)
    for series in (z, np.diff(z, axis=1), np.diff(z, 2, axis=1)):
        fast, growth = est._lag1_sums(series)
        assert np.all(growth < 10.0)
        np.testing.assert_allclose(
            fast, est._lag1(series, np.empty(series.shape)), rtol=0, atol=1e-12
        )


def test_noise_work_decimation_is_a_slice_of_the_phase():
    x = np.arange(6 * 300_001, dtype=np.float64).reshape(6, -1)
    work = est.NoiseWork.of(x)
    assert (x.shape[1] + work.step - 1) // work.step <= est.NOISE_ID_MAX_POINTS
    for m in (1, 3, work.step, 2 * work.step, 3 * work.step, 5 * work.step + 1):
        want = x[:, : m * est.NOISE_ID_MAX_POINTS : m]
        np.testing.assert_array_equal(work.decimated(m), want)


def _straight_solve(a, target, w, iters=60, fixed=None, start=None):
    """The projected Gauss-Newton of ``allan_fit._solve`` as written before: every cost
    evaluated afresh (the same NNLS, :func:`imupipe.stages.allan.nnls.nnls`)."""
    from imupipe.stages.allan.nnls import nnls

    sw = np.sqrt(w)
    level = np.exp(target)
    rel = a / level[:, None]
    scale = 1.0 / rel.max(axis=0)
    a_s = a * scale
    off = np.zeros(len(target)) if fixed is None else np.asarray(fixed, dtype=np.float64)
    p = a.shape[1]

    def cost(u):
        mu = a_s @ u + off
        if not mu.min() > 0:
            return np.inf
        r = np.log(mu) - target
        return float(r @ (w * r))

    def descend(u):
        f = cost(u)
        for _ in range(iters):
            mu = a_s @ u + off
            jac = a_s / mu[:, None]
            new = nnls(sw[:, None] * jac, sw * (jac @ u - (np.log(mu) - target)))
            step = new - u
            lam = 1.0
            while lam > 1e-6 and cost(u + lam * step) >= f:
                lam *= 0.5
            if lam <= 1e-6:
                break
            trial = u + lam * step
            ft = cost(trial)
            done = f - ft <= 1e-9 * max(f, 1e-300)
            u, f = trial, ft
            if done:
                break
        u = np.maximum(u, 0.0)
        return u, cost(u)

    if start is not None:
        starts = [np.maximum(np.asarray(start, dtype=np.float64) / scale, 1e-12)]
    else:
        first = nnls(sw[:, None] * rel * scale, sw * np.maximum(1.0 - off / level, 0.0))
        starts = [first] if np.any(first > 0) else [np.full(p, 1.0 / p), np.ones(p)]
    u, f = min((descend(s0) for s0 in starts), key=lambda item: item[1])
    return u * scale, f


def _fit_problems():
    """Log-space problems of simulated curves: white + random walk (+ bias instability,
    quantisation, ramp), every subset of the terms, with and without a fixed K share."""
    from imupipe.stages.allan import fit

    rng = np.random.default_rng(17)
    taus = np.logspace(-2.4, 3.2, 22)
    for curve in range(8):
        c = np.array([3e-10, 1e-7, 2e-9 * (curve % 2), 1e-11, 1e-15 * (curve % 3 == 0)])
        c *= np.exp(rng.normal(0.0, 0.5, 5))
        var = sum(ci * taus**pw for ci, pw in zip(c, (-2, -1, 0, 1, 2), strict=True))
        target = np.log(var) + rng.normal(0.0, 0.05, len(taus)) * np.sqrt(taus)
        w = fit.density_weights(taus) / (0.01 + 0.001 * taus)
        problem = fit._Problem(taus, target, w)
        for size in range(1, 6):
            for terms in itertools.combinations(fit.TERMS, size):
                yield problem, list(terms), None, None
        k_unit = fit.FACTORS["K"] * taus
        for k in (0.0, 1e-12, 1e-11, 1e-10):
            yield problem, ["Q", "N", "B", "R"], k * k_unit, np.array([1e-10, 1e-7, 1e-9, 1e-16])


def test_gauss_newton_is_the_straightforward_one_bit_for_bit():
    """``_solve`` (scaled columns built once, each cost evaluated once) against the
    straightforward loop: the same coefficients and cost, bit for bit, on every subset of the
    terms and on profile solves."""
    from imupipe.stages.allan import fit

    count = 0
    for problem, terms, fixed, start in _fit_problems():
        a = problem.columns(terms)
        iters = 60 if fixed is None else 30
        want = _straight_solve(a, problem.target, problem.w, iters, fixed, start)
        got = fit._solve(a, problem.target, problem.w, iters, fixed, start)
        np.testing.assert_array_equal(got[0], want[0])
        assert got[1] == want[1]
        count += 1
    assert count > 250


def test_stillness_with_the_stage_shortcuts_is_the_same():
    """The allan stage's call (blocks found by bisection on increasing stamps, the gyro means
    it already has) gives the same figures and blocks as the general one, with jitter, lost
    samples and a gap."""
    from imupipe.stages.blocks import block_starts
    from imupipe.stages.stillness import stillness

    rng = np.random.default_rng(4)
    step = np.full(20_000, 2_500_000) + rng.integers(-400_000, 400_000, 20_000)
    step[rng.integers(0, len(step), 30)] *= 2
    step[12_345] = 3_700_000_000  # a gap of several blocks
    t_ns = 1_700_000_000_123_456_789 + np.r_[0, np.cumsum(step)]
    gyro = [rng.standard_normal(len(t_ns)) * 0.01 for _ in range(3)]
    accel = [rng.standard_normal(len(t_ns)) * 0.02 + g for g in (0.0, 0.0, 9.81)]
    np.testing.assert_array_equal(
        block_starts(t_ns, window_s=1.0, increasing=True), block_starts(t_ns, window_s=1.0)
    )
    a = stillness(t_ns, gyro, accel)
    b = stillness(t_ns, gyro, accel, increasing=True, gyro_means=[c.mean() for c in gyro])
    assert (a.excursion, a.accel_spread) == (b.excursion, b.accel_spread)
    for field in ("t_ns", "means", "counts", "starts"):
        np.testing.assert_array_equal(getattr(a.gyro_1s, field), getattr(b.gyro_1s, field))


@pytest.mark.parametrize("given", [None, "2"])
def test_the_command_line_sets_mimalloc_before_pyarrow_loads(given):
    """``imupipe`` starts mimalloc (pyarrow's default pool, Rerun's allocator) without eager
    arena commits (:data:`imupipe.pipeline.cli.EAGER_COMMIT`): set before any command's module,
    and so pyarrow, is imported (mimalloc reads it once, when it starts); a value the user set
    is kept."""
    import os

    code = (
        "import os, sys\n"
        "import imupipe.pipeline.cli as cli\n"
        "before = 'pyarrow' in sys.modules\n"
        "try:\n"
        "    cli.main(['--version'])\n"
        "except SystemExit:\n"
        "    pass\n"
        "print(before, os.environ.get('MIMALLOC_ARENA_EAGER_COMMIT'))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "MIMALLOC_ARENA_EAGER_COMMIT"}
    if given is not None:
        env["MIMALLOC_ARENA_EAGER_COMMIT"] = given
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["False", given or "0"]
