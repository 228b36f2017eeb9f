"""compare: rows line up by the params of a comparable run, outcomes are episode-weighted with Wilson intervals,
accuracy comes from the latest runs of the row's own predictor and gradient source."""
import logging

import mlflow
import numpy as np
import pytest
from test_batch import wilson_by_roots

from conftest import compose_cfg
from planner.compare import run


def log(experiment, params, metrics):
    mlflow.set_experiment(experiment)
    with mlflow.start_run():
        mlflow.log_params(params)
        mlflow.log_metrics(metrics)


def test_empty_store_says_what_to_run(store):
    with pytest.raises(SystemExit) as e:
        run(compose_cfg("compare", [f"out_dir={store}"]))
    assert e.value.code == 2


def test_table_weights_episodes_and_picks_latest_accuracy(store, caplog):
    caplog.set_level(logging.INFO)
    base = {"method": "admm", "zstep": "sqp", "scenario": "two_lane"}
    for merged, ms in [(1, 10.0), (0, 30.0), (1, 20.0)]:
        log("planner", {**base, "gradients": "surrogate", "predictor": "teacher"}, {"merged": merged, "collision": 0, "step_median_ms": ms,
                                                            "step_p95_ms": 2 * ms, "t_merge_s": 9, "C_max": 60, "d_min_m": 4.0 + ms / 100})
    log("planner", {**base, "gradients": "surrogate", "predictor": "teacher"}, {"episodes": 10, "merged": 0.5, "collision": 0.1, "step_median_ms": 40.0,
                                                        "step_p95_ms": 80.0, "t_merge_s": 12, "C_max": 70, "d_min_m": 3.9})
    log("planner", {**base, "gradients": "teacher"}, {"merged": 1, "collision": 0, "step_median_ms": 900.0, "step_p95_ms": 990.0,
                                                      "t_merge_s": 8, "C_max": 55, "d_min_m": 4.2})
    log("distill", {"model": "teacher"}, {"ade_1step_m": 0.9, "ade_rollout_m": 9.0})
    log("distill", {"model": "teacher"}, {"ade_1step_m": 0.1, "ade_rollout_m": 0.5})
    log("surrogate", {"source": "teacher"}, {"grad_cosine": 0.97, "grad_rel_err": 0.2, "grad_rel_err_lo": 0.15,
                                             "grad_rel_err_hi": 0.25, "jac_rel_err": 0.3, "grad_rel_err_cv": 0.34,
                                             "grad_rel_err_mean": 0.35, "react_rel_err": 0.6, "react_rel_err_mean": 1.1})
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    assert list(df["gradients"]) == ["surrogate", "teacher"]
    s = df.iloc[0]
    assert s["n_episodes"] == 13
    assert s["merged_rate"] == pytest.approx((1 + 0 + 1 + 0.5 * 10) / 13)
    assert s["collision_rate"] == pytest.approx(1.0 / 13)
    assert s["t_merge_s"] == pytest.approx((9 * 2 + 12 * 0.5 * 10) / (2 + 0.5 * 10))  # merged episodes only
    assert s["step_median_ms"] == pytest.approx(np.median([10.0, 30.0, 20.0, 40.0]))
    assert s["d_min_m"] == pytest.approx(3.9)
    assert s["grad_cosine"] == 0.97 and s["ade_1step_m"] == 0.1
    assert (s["grad_rel_err"], s["grad_rel_err_lo"], s["grad_rel_err_hi"], s["react_rel_err"]) == (0.2, 0.15, 0.25, 0.6)
    t = df.iloc[1]  # the teacher: its own autodiff is the reference, so no gradient error is claimed for it
    assert np.isnan(t["grad_cosine"]) and np.isnan(t["grad_rel_err"]) and np.isnan(t["jac_rel_err"])
    assert (df["grad_rel_err_cv"] == 0.34).all() and (df["react_rel_err_mean"] == 1.1).all()  # the baselines on every row
    assert t["ade_1step_m"] == 0.1 and t["ade_rollout_m"] == 0.5 and t["n_episodes"] == 1 and t["step_median_ms"] == 900.0
    assert (store / "compare.png").read_bytes()[:4] == b"\x89PNG"
    assert (store / "compare.csv").read_text().splitlines()[0].startswith("scenario,world,gradients,predictor,method")
    assert s["n_runs"] == 4 and len(s["runs"].split()) == 4
    assert "surrogate" in caplog.text and "0.34" in caplog.text  # the cv baseline printed beside the rows
    runs = mlflow.search_runs(experiment_names=["compare"])
    assert len(runs) == 1 and runs.iloc[0]["status"] == "FINISHED"
    assert runs.iloc[0]["tags.mlflow.runName"] == "compare-planner-every scenario"
    logged = {f.path for f in mlflow.artifacts.list_artifacts(run_id=runs.iloc[0]["run_id"])}
    assert {"compare_table.json", "compare.csv", "compare.png"} <= logged  # the table in MLflow's own table view too


def test_rows_split_by_setup_and_accuracy_follows_the_predictor(store):
    base = {"method": "admm", "zstep": "sqp", "scenario": "two_lane", "world": "reactive", "mpc.T_p": "8", "seed": "0",
            "episodes": "0"}
    ok = {"merged": 1, "collision": 0, "step_median_ms": 5.0, "step_p95_ms": 9.0, "t_merge_s": 11, "C_max": 60, "d_min_m": 4.0}
    for steps, rho in [("60", "100"), ("60", "100"), ("2", "100"), ("60", "0.0")]:
        log("planner", {**base, "gradients": "cv", "predictor": "cv", "max_steps": steps, "mpc.admm.rho": rho}, ok)
    log("planner", {**base, "gradients": "surrogate", "predictor": "teacher", "max_steps": "60", "mpc.admm.rho": "100"},
        {**ok, "episodes": 40, "merged": 0.75})
    log("planner", {**base, "gradients": "surrogate", "max_steps": "60", "mpc.admm.rho": "100"}, ok)  # its default predictor
    log("distill", {"model": "teacher"}, {"ade_1step_m": 0.002, "ade_rollout_m": 0.04, "ade_1step_m_cv": 0.007,
                                          "ade_rollout_m_cv": 0.107})
    log("distill", {"model": "student"}, {"ade_1step_m": 0.003, "ade_rollout_m": 0.05})
    log("surrogate", {"source": "teacher"}, {"grad_rel_err": 0.2, "grad_rel_err_over_student": 0.25})
    log("interaction", {"source": "cv"}, {"react_corr": 0.0, "react_corr_jac": 0.0, "react_hit": 0.1})
    log("interaction", {"source": "surrogate"}, {"react_corr": 0.6, "react_corr_jac": 0.3, "react_hit": 0.4})
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    cv = df[df["gradients"] == "cv"].set_index(["max_steps", "mpc.admm.rho"])
    assert len(cv) == 3 and list(cv.loc[("60", "100"), ["n_runs", "n_episodes"]]) == [2, 2]  # only the two equal runs pooled
    assert cv.loc[("2", "100"), "n_runs"] == 1 and cv.loc[("60", "0.0"), "n_runs"] == 1
    assert (cv["ade_rollout_m"] == 0.107).all() and cv["react_corr_jac"].eq(0.0).all()  # constant velocity's, not the teacher's
    assert cv["grad_cosine"].isna().all()
    sur = df[(df["gradients"] == "surrogate") & (df["predictor"] == "teacher")].iloc[0]
    assert sur["ade_rollout_m"] == 0.04 and sur["react_corr"] == 0.6 and sur["react_corr_jac"] == 0.3
    assert sur["grad_rel_err"] == 0.2
    paired = df[(df["gradients"] == "surrogate") & (df["predictor"] != "teacher")].iloc[0]  # the student's values
    assert paired["ade_rollout_m"] == 0.05 and paired["grad_rel_err"] == 0.25
    lo, hi = sur["merged_lo"], sur["merged_hi"]  # Wilson, 30 of 40: 0.5981 .. 0.8581
    assert lo == pytest.approx(0.5981, abs=1e-4) and hi == pytest.approx(0.8581, abs=1e-4)
    assert (store / "compare.png").read_bytes()[:4] == b"\x89PNG"


def test_printed_table_is_short_and_the_csv_keeps_every_column(store, caplog):
    caplog.set_level(logging.INFO)
    base = {"method": "admm", "zstep": "sqp", "scenario": "dense", "gradients": "cv", "episodes": "40"}
    for mpc, courteous, ms in [("paper", 0.0, 2.8), ("courteous", 0.825, 7.2)]:
        log("planner", {**base, "mpc": mpc}, {"episodes": 40, "courteous": courteous, "merged": 0.9, "collision": 0.0,
                                              "t_merge_s": 30.0, "fallbacks": 0.5, "step_median_ms": ms, "step_p95_ms": 2 * ms})
    log("surrogate", {"source": "teacher"}, {"ramp_grad_rel_err_cv": 0.268, "ramp_grad_rel_err_cv_lo": 0.2,
                                             "ramp_grad_rel_err_cv_hi": 0.3, "ramp_grad_rel_err_mean": 0.27})
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    lines = caplog.text.split("every row: ")[1].splitlines()
    assert "d b_i/dZ error of the baselines: cv 0.268, mean Jacobian 0.270" in lines[0]
    header = lines[1].split()
    assert header[:3] == ["gradients", "method", "mpc"] and "react_corr_jac" not in header and "ade_rollout_m" not in header
    row = next(line for line in lines[2:] if " courteous " in line)
    lo, hi = wilson_by_roots(33, 40)  # 82.5% of 40 episodes
    assert f"82.5 [{100 * lo:.1f}, {100 * hi:.1f}]" in row and "0.268 [0.200, 0.300]" in row and "7.2/14.4" in row
    assert max(len(line) for line in lines[1:4]) < 120  # a terminal shows it
    columns = (store / "compare.csv").read_text().splitlines()[0].split(",")
    assert {"react_corr_jac", "ade_rollout_m", "C_max", "courteous_lo", "step_p95_ms"} <= set(columns) == set(df.columns)


def test_runs_whose_models_differ_are_never_pooled(store):
    base = {"method": "admm", "zstep": "sqp", "scenario": "dense", "gradients": "surrogate", "predictor": "student"}
    ok = {"merged": 1, "courteous": 1, "collision": 0, "step_median_ms": 9.0, "step_p95_ms": 12.0}
    for digest, C in [("a" * 64, 274.8), ("b" * 64, 70.4), ("a" * 64, 274.8)]:  # surrogate.onnx replaced in between
        log("planner", {**base, "sha256.surrogate.onnx": digest, "models_dir": "models"}, {**ok, "C_max": C})
    df = run(compose_cfg("compare", [f"out_dir={store}", "scenario=dense"])).set_index("sha256.surrogate.onnx")
    assert list(df["n_runs"]) == [2, 1] and list(df["C_max"]) == [274.8, 70.4]
