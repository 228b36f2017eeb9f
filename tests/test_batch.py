"""Batch statistics: one MLflow run per method with rates and a per-episode CSV; a crashing episode is counted (and, when
tolerated, not fatal); the rates, means and their intervals against independent computations."""
import csv
import itertools

import mlflow
import numpy as np
import pytest
from scipy import stats

from conftest import compose_cfg
from planner import batch, cli, setup


def wilson_by_roots(k, n, z=stats.norm.ppf(0.975)):
    """The Wilson interval as the two rates p the score test does not reject: roots of (k/n - p)^2 = z^2 p (1 - p) / n."""
    p_hat = k / n
    return sorted(np.roots([1 + z * z / n, -(2 * p_hat + z * z / n), p_hat**2]).real)


def test_aggregate_of_hand_built_rows():
    row = lambda merged, collision, t_merge, C_max, fallbacks, d_min, b, nan=0: dict(
        seed=0, merged=merged, collision=collision, t_merge=t_merge, C_max=C_max, fallbacks=fallbacks, d_min_m=d_min, crash=0,
        nan=nan, error="", b_imposed_max=b, courteous=float(merged and not collision and b <= 4.0), ttc_min=d_min)
    rows = [row(1.0, 0.0, 10.0, 0.1, 0.0, 2.0, 1.0), row(1.0, 0.0, 12.0, 0.2, 1.0, 1.5, 6.0),
            row(1.0, 1.0, 14.0, 0.3, 0.0, 0.4, 2.0, nan=1),
            row(0.0, 0.0, 30.0, 0.4, 3.0, 3.0, 0.5),  # never merged: its t_merge (the steps it drove) is no merge time
            dict(seed=4, crash=1, nan=0, error="RuntimeError: boom")]
    m = batch.aggregate(rows, [1.0, 2.0, 3.0, 4.0, 100.0], [3, 5])
    assert (m["episodes"], m["crashes"], m["nans"], m["d_min_m"]) == (5, 1, 1, 0.4)
    assert (m["step_ms_median"], m["admm_iters_mean"]) == (3.0, 4.0)
    assert m["step_ms_p95"] == pytest.approx(4 + 0.8 * 96)  # linear interpolation at rank 0.95 * 4 = 3.8
    assert m["merged"] == 0.75 and m["collision"] == 0.25  # over the 4 finished episodes
    assert m["courteous"] == 0.25 and [m["courteous_lo"], m["courteous_hi"]] == pytest.approx(wilson_by_roots(1, 4))
    assert m["ttc_min"] == 0.4
    assert [m["merged_lo"], m["merged_hi"]] == pytest.approx(wilson_by_roots(3, 4))
    assert [m["collision_lo"], m["collision_hi"]] == pytest.approx(wilson_by_roots(1, 4))
    assert [m["merged_lo"], m["merged_hi"]] == pytest.approx([0.3006, 0.9544], abs=1e-4)  # a textbook value
    for key, values in (("t_merge", [10.0, 12.0, 14.0]), ("C_max", [0.1, 0.2, 0.3, 0.4]), ("fallbacks", [0.0, 1.0, 0.0, 3.0]),
                        ("b_imposed_max", [1.0, 6.0, 2.0, 0.5])):
        # the exact percentile bootstrap: the quantiles of the means of all n^n equally likely resamples
        every = [np.mean(r) for r in itertools.product(values, repeat=len(values))]
        lo, hi = np.quantile(every, [0.025, 0.975], method="inverted_cdf")
        assert [m[key], m[f"{key}_lo"], m[f"{key}_hi"]] == pytest.approx([np.mean(values), lo, hi]), key


def test_a_skewed_count_gets_an_interval_that_stays_at_or_above_zero():
    """19 episodes without a fallback and one with 3: mean 0.15, whose Student t interval reaches below 0."""
    rows = [dict(seed=i, crash=0, nan=0, merged=1.0, collision=0.0, courteous=1.0, t_merge=10.0, C_max=1.0, d_min_m=2.0,
                 ttc_min=2.0, b_imposed_max=1.0, fallbacks=3.0 if i == 7 else 0.0) for i in range(20)]
    m = batch.aggregate(rows, [1.0], [1])
    values = [r["fallbacks"] for r in rows]
    assert stats.t.interval(0.95, 19, loc=np.mean(values), scale=stats.sem(values))[0] < 0  # what the t interval said
    assert m["fallbacks"] == pytest.approx(0.15)
    assert 0 <= m["fallbacks_lo"] <= m["fallbacks"] <= m["fallbacks_hi"]
    # a resample's mean is 3 k / 20 with k ~ Binomial(20, 1/20) episodes that fell back: its 2.5% and 97.5% quantiles
    assert [m["fallbacks_lo"], m["fallbacks_hi"]] == pytest.approx(3 / 20 * stats.binom.ppf([0.025, 0.975], 20, 1 / 20))


def batch_cfg(tmp_path, *overrides):
    """A tiny random-scenario batch: short episodes of the fast NNMPC baseline."""
    return compose_cfg("planner", ["scenario=random", "gradients=analytic", "method=nnmpc", "max_steps=8",
                                   f"out_dir={tmp_path}", *overrides])


def test_batch_logs_one_run_with_rates_csv_and_histograms(tmp_path):
    m = cli.run(batch_cfg(tmp_path, "episodes=4", "n_jobs=2", "seed=10"))["nnmpc"]
    assert m["episodes"] == 4 and m["crashes"] == 0 and m["nans"] == 0
    rows = list(csv.DictReader(open(tmp_path / "episodes_nnmpc_analytic_random.csv")))
    assert sorted(int(r["seed"]) for r in rows) == [10, 11, 12, 13]
    for k in ("courteous", "merged", "collision"):  # the run's rates are its CSV's
        assert m[k] == np.mean([float(r[k]) for r in rows])
    assert m["d_min_m"] == pytest.approx(min(float(r["d_min_m"]) for r in rows))
    assert len(list(tmp_path.glob("hist_nnmpc_analytic_random_*.png"))) == len(batch.FIGURES)
    runs = mlflow.search_runs(experiment_names=["planner"], filter_string="params.scenario = 'random' and params.episodes = '4'")
    assert len(runs) == 1 and runs["params.method"].iloc[0] == "nnmpc" and runs["metrics.episodes"].iloc[0] == 4


def test_a_crashing_episode_is_counted_and_the_batch_goes_on(tmp_path, monkeypatch):
    real = setup.drive

    def flaky(cfg, scenario, source, s, method, seed=None):
        if seed == 1:
            raise RuntimeError("boom in episode 1")
        return real(cfg, scenario, source, s, method, seed=seed)

    monkeypatch.setattr(setup, "drive", flaky)  # n_jobs=1: joblib runs in this process, so the patch applies
    m = cli.run(batch_cfg(tmp_path, "episodes=3", "n_jobs=1", "tolerate_crashes=true"))["nnmpc"]
    rows = {r["seed"]: r for r in csv.DictReader(open(tmp_path / "episodes_nnmpc_analytic_random.csv"))}
    assert m["crashes"] == 1 and m["episodes"] == 3
    assert m["merged"] == (float(rows["0"]["merged"]) + float(rows["2"]["merged"])) / 2  # rates over the 2 that finished
    assert rows["1"]["crash"] == "1" and rows["1"]["error"] == "RuntimeError: boom in episode 1"
    assert rows["0"]["crash"] == rows["2"]["crash"] == "0"
