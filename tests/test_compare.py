"""compare: rows line up by params, outcomes are episode-weighted, accuracy comes from the latest model runs."""
import logging

import mlflow
import numpy as np
import pytest

from conftest import compose_cfg
from planner.compare import run


def log(experiment, params, metrics):
    mlflow.set_experiment(experiment)
    with mlflow.start_run():
        mlflow.log_params(params)
        mlflow.log_metrics(metrics)


@pytest.fixture()
def store(tmp_path, monkeypatch):
    uri = f"sqlite:///{tmp_path / 'compare.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    mlflow.set_tracking_uri(uri)
    return tmp_path


def test_empty_store_says_what_to_run(store):
    with pytest.raises(SystemExit) as e:
        run(compose_cfg("compare", [f"out_dir={store}"]))
    assert e.value.code == 2


def test_table_weights_episodes_and_picks_latest_accuracy(store, caplog):
    caplog.set_level(logging.INFO)
    base = {"method": "admm", "zstep": "sqp", "scenario": "two_lane"}
    for merged, ms in [(1, 10.0), (0, 30.0), (1, 20.0)]:
        log("planner", {**base, "gradients": "surrogate"}, {"merged": merged, "collision": 0, "step_ms_median": ms,
                                                            "step_ms_p95": 2 * ms, "t_merge": 9, "C_max": 60, "d_min_m": 4.0 + ms / 100})
    log("planner", {**base, "gradients": "surrogate"}, {"episodes": 10, "merged": 0.5, "collision": 0.1, "step_ms_median": 40.0,
                                                        "step_ms_p95": 80.0, "t_merge": 12, "C_max": 70, "d_min_m": 3.9})
    log("planner", {**base, "gradients": "teacher"}, {"merged": 1, "collision": 0, "step_ms_median": 900.0, "step_ms_p95": 990.0,
                                                      "t_merge": 8, "C_max": 55, "d_min_m": 4.2})
    log("distill", {"model": "teacher"}, {"ade_1step_m": 0.9, "ade_rollout_m": 9.0})
    log("distill", {"model": "teacher"}, {"ade_1step_m": 0.1, "ade_rollout_m": 0.5})
    log("surrogate", {"source": "teacher"}, {"grad_cosine": 0.97, "grad_rel_err": 0.2, "jac_rel_err": 0.3})
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    assert list(df["gradients"]) == ["surrogate", "teacher"]
    s = df.iloc[0]
    assert s["episodes"] == 13
    assert s["merged_rate"] == pytest.approx((1 + 0 + 1 + 0.5 * 10) / 13)
    assert s["collision_rate"] == pytest.approx(1.0 / 13)
    assert s["t_merge"] == pytest.approx((9 * 2 + 12 * 0.5 * 10) / (2 + 0.5 * 10))  # merged episodes only
    assert s["step_ms_median"] == pytest.approx(np.median([10.0, 30.0, 20.0, 40.0]))
    assert s["d_min_m"] == pytest.approx(3.9)
    assert s["grad_cosine"] == 0.97 and s["ade_1step_m"] == 0.1
    t = df.iloc[1]  # the teacher: its own autodiff is the reference, so no gradient error is claimed for it
    assert np.isnan(t["grad_cosine"]) and np.isnan(t["grad_rel_err"]) and np.isnan(t["jac_rel_err"])
    assert t["ade_1step_m"] == 0.1 and t["ade_rollout_m"] == 0.5 and t["episodes"] == 1 and t["step_ms_median"] == 900.0
    assert (store / "compare.png").read_bytes()[:4] == b"\x89PNG"
    assert (store / "compare.csv").read_text().splitlines()[0].startswith("gradients,method,zstep,episodes")
    assert "surrogate" in caplog.text and "0.97" in caplog.text
    runs = mlflow.search_runs(experiment_names=["compare"])
    assert len(runs) == 1 and runs.iloc[0]["status"] == "FINISHED"
