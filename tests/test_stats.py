"""core.stats against independent implementations: Wilson against the roots of the score test and scipy's binomtest, the
t interval against scipy.stats.t, the bootstrap against scipy.stats.bootstrap; outcome rows pooled as batch, results
and compare report them."""
import numpy as np
import pytest
from scipy import stats as sp

from core.stats import MEANS, RATES, bootstrap, mean_ci, outcomes, wilson

nan = float("nan")


@pytest.mark.parametrize("k, n", [(0, 1), (0, 10), (3, 10), (10, 10), (30, 40), (1, 1000), (517, 1000)])
def test_wilson_is_the_score_test_interval(k, n):
    z = sp.norm.ppf(0.975)
    p = k / n
    # the ends are the p with |p_hat - p| = z sqrt(p (1 - p) / n): roots of a quadratic in p
    ends = np.sort(np.roots([1 + z * z / n, -(2 * p + z * z / n), p * p]).real)
    assert wilson(k, n) == pytest.approx(tuple(ends), abs=1e-12)
    ci = sp.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
    assert wilson(k, n) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_wilson_at_the_ends_and_of_counts_held_as_floats():
    z2 = sp.norm.ppf(0.975) ** 2
    assert wilson(0.0, 10.0) == pytest.approx((0.0, z2 / (10 + z2)), abs=1e-12)  # no hit: hi = z^2 / (n + z^2)
    assert wilson(10, 10) == pytest.approx((10 / (10 + z2), 1.0), abs=1e-12)
    assert wilson(0.7 * 10, 10.0) == wilson(7, 10)  # 7.000000000000001: a batch's rate times its episodes: a count up to rounding


def test_wilson_of_no_trials_is_nan():
    assert np.isnan(wilson(0, 0)).all()


def test_mean_ci_is_the_t_interval_of_the_finite_values():
    v = np.random.default_rng(0).normal(3.0, 2.0, 9)
    m, lo, hi = mean_ci([*v[:4], nan, np.inf, *v[4:], -np.inf])
    assert m == pytest.approx(v.mean())
    assert (lo, hi) == pytest.approx(sp.t.interval(0.95, len(v) - 1, loc=v.mean(), scale=sp.sem(v)), rel=1e-12)


def test_mean_ci_of_none_or_one_value():
    assert np.isnan(mean_ci([])).all() and np.isnan(mean_ci([nan, np.inf])).all()
    assert mean_ci([nan, 2.5]) == (2.5, 2.5, 2.5)


def test_bootstrap_matches_scipy_percentile_bootstrap():
    x = np.random.default_rng(3).normal(0.0, 1.0, 50)
    ref = sp.bootstrap((x,), np.mean, method="percentile", n_resamples=4000, rng=np.random.default_rng(4)).confidence_interval
    # one group resampled within, or single-item groups drawn whole: both the ordinary bootstrap of the items
    for groups, within in (([x], True), (x[:, None], False)):
        lo, hi = bootstrap(groups, np.mean, 4000, 5, within=within)
        assert lo == pytest.approx(ref.low, abs=0.03) and hi == pytest.approx(ref.high, abs=0.03)


def test_bootstrap_is_seeded_and_a_generator_goes_on():
    groups = [[1.0, 2.0, 4.0], [3.0, 8.0]]
    assert (bootstrap(groups, np.mean, 200, 7) == bootstrap(groups, np.mean, 200, 7)).all()
    rng = np.random.default_rng(7)
    assert (bootstrap(groups, np.mean, 200, rng) == bootstrap(groups, np.mean, 200, 7)).all()
    assert (bootstrap(groups, np.mean, 200, rng) != bootstrap(groups, np.mean, 200, 7)).any()  # rng moved on


def test_bootstrap_edge_cases():
    assert np.isnan(bootstrap([], np.mean, 100, 0)).all() and np.isnan(bootstrap([[], []], np.mean, 100, 0)).all()
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    assert list(bootstrap([[], [4.0]], np.mean, 100, rng)) == [4.0, 4.0]
    assert rng.bit_generator.state == state  # nothing to resample draws nothing from a shared stream
    # a draw that picks the same single-item group twice has no spread: its NaN statistic is left out
    spread = lambda a: a.mean() if a.min() < a.max() else nan
    assert list(bootstrap([[1.0], [2.0]], spread, 200, 0, within=False)) == [1.5, 1.5]


def episode(merged, t_merge, C_max=60.0, collision=0.0, fallbacks=0.0):
    return {"merged": merged, "collision": collision, "t_merge": t_merge, "C_max": C_max, "fallbacks": fallbacks}


def test_outcomes_of_episodes():
    rows = [episode(1.0, 20.0, 50.0), episode(0.0, 60.0, nan, 1.0), episode(1.0, 24.0, 70.0, fallbacks=2.0),
            episode(1.0, 31.0, 65.0), episode(0.0, 60.0, 80.0, fallbacks=1.0)]
    o = outcomes([rows])
    ci = sp.binomtest(3, 5).proportion_ci(method="wilson")
    assert o["merged"] == 0.6 and (o["merged_lo"], o["merged_hi"]) == pytest.approx((ci.low, ci.high))
    assert o["collision"] == 0.2
    t = np.array([20.0, 24.0, 31.0])  # merged episodes only
    assert o["t_merge"] == pytest.approx(t.mean())
    assert (o["t_merge_lo"], o["t_merge_hi"]) == pytest.approx(sp.t.interval(0.95, 2, loc=t.mean(), scale=sp.sem(t)))
    assert o["C_max"] == pytest.approx(66.25) and o["fallbacks"] == pytest.approx(0.6)
    # per training with resamples: the bootstrap over trainings then episodes, of the same merged-only values
    b = outcomes([rows[:2], rows[2:]], resamples=300, seed=1)
    assert b["merged"] == o["merged"] and b["t_merge"] == o["t_merge"]
    assert (b["t_merge_lo"], b["t_merge_hi"]) == tuple(bootstrap([[20.0], [24.0, 31.0]], np.mean, 300, 1))
    assert b["t_merge_lo"] < b["t_merge"] < b["t_merge_hi"]


def test_outcomes_of_batches_are_episode_weighted_without_mean_intervals():
    rows = [{**episode(0.75, 12.0), "n": 40}, {**episode(1.0, 9.0, 80.0), "n": 1}, {**episode(0.0, 60.0), "n": 3}]
    o = outcomes([rows], weight="n", means=("t_merge", "C_max"))
    ci = sp.binomtest(31, 44).proportion_ci(method="wilson")
    assert o["merged"] == pytest.approx(31 / 44) and (o["merged_lo"], o["merged_hi"]) == pytest.approx((ci.low, ci.high))
    assert o["t_merge"] == pytest.approx((12.0 * 30 + 9.0) / 31) and o["C_max"] == pytest.approx((60.0 * 43 + 80.0) / 44)
    assert np.isnan([o["t_merge_lo"], o["t_merge_hi"], o["C_max_lo"], o["C_max_hi"]]).all()
    unlogged = outcomes([[*rows, {"n": 5, "merged": nan, "t_merge": 30.0}]], weight="n", means=("t_merge",))
    assert np.isnan([unlogged["merged"], unlogged["merged_lo"], unlogged["collision"]]).all()
    assert unlogged["t_merge"] == pytest.approx(o["t_merge"])  # no merges known, so no t_merge counted


def test_outcomes_of_nothing_are_nan():
    for groups in ([], [[]], [[], []]):
        o = outcomes(groups, resamples=50, seed=0)
        assert len(o) == 3 * (len(RATES) + len(MEANS)) and np.isnan(list(o.values())).all()
