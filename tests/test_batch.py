"""Batch statistics: one MLflow run per method with rates and a per-episode CSV; a crashing episode is counted, not fatal."""
import csv

import mlflow

from conftest import compose_cfg
from planner import cli, setup


def batch_cfg(tmp_path, *overrides):
    """A tiny random-scenario batch: short episodes of the fast NNMPC baseline."""
    return compose_cfg("planner", ["scenario=random", "gradients=analytic", "method=nnmpc", "max_steps=8",
                                   f"out_dir={tmp_path}", *overrides])


def test_batch_logs_one_run_with_rates_csv_and_histograms(tmp_path):
    m = cli.run(batch_cfg(tmp_path, "episodes=4", "n_jobs=2", "seed=10"))["nnmpc"]
    assert m["episodes"] == 4 and m["crashes"] == 0 and m["nans"] == 0
    assert 0 <= m["merged"] <= 1 and 0 <= m["collision"] <= 1 and m["step_ms_p95"] >= m["step_ms_median"] > 0
    rows = list(csv.DictReader(open(tmp_path / "episodes_nnmpc_analytic_random.csv")))
    assert sorted(int(r["seed"]) for r in rows) == [10, 11, 12, 13]
    assert len(list(tmp_path.glob("hist_nnmpc_analytic_random_*.png"))) == 6
    runs = mlflow.search_runs(experiment_names=["planner"], filter_string="params.scenario = 'random' and params.episodes = '4'")
    assert len(runs) == 1 and runs["params.method"].iloc[0] == "nnmpc" and runs["metrics.episodes"].iloc[0] == 4


def test_a_crashing_episode_is_counted_and_the_batch_goes_on(tmp_path, monkeypatch):
    real = setup.drive

    def flaky(cfg, scenario, source, s, method, seed=None):
        if seed == 1:
            raise RuntimeError("boom in episode 1")
        return real(cfg, scenario, source, s, method, seed=seed)

    monkeypatch.setattr(setup, "drive", flaky)  # n_jobs=1: joblib runs in this process, so the patch applies
    m = cli.run(batch_cfg(tmp_path, "episodes=3", "n_jobs=1"))["nnmpc"]
    assert m["crashes"] == 1 and m["episodes"] == 3 and 0 <= m["merged"] <= 1  # rates over the 2 that finished
    rows = {r["seed"]: r for r in csv.DictReader(open(tmp_path / "episodes_nnmpc_analytic_random.csv"))}
    assert rows["1"]["crash"] == "1" and rows["1"]["error"] == "RuntimeError: boom in episode 1"
    assert rows["0"]["crash"] == rows["2"]["crash"] == "0"
