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
    assert (store / "compare.csv").read_text().splitlines()[0].startswith("label,scenario,world,gradients,predictor,method")
    assert s["n_runs"] == 4 and len(s["runs"].split()) == 4
    assert "surrogate" in caplog.text and "0.34" in caplog.text  # the cv baseline printed beside the rows
    runs = mlflow.search_runs(experiment_names=["compare"])
    assert len(runs) == 1 and runs.iloc[0]["status"] == "FINISHED"
    assert runs.iloc[0]["tags.mlflow.runName"] == "compare-all-5runs"  # what it compares: every scenario, 5 planner runs
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
    assert list(df["label"]) == ["surrogate/admm/dense (surrogate.onnx=aaaaaaaa)", "surrogate/admm/dense (surrogate.onnx=bbbbbbbb)"]
    assert mlflow.search_runs(experiment_names=["compare"]).iloc[0]["tags.mlflow.runName"] == "compare-dense-3runs"


def demo_store():
    """Planner runs as `make demo` logs them (each run's every top-level setting, the model hashes and model runs of the
    sources that read models), the iterate-recording run of its MODELS among them."""
    same = {"scenario": "dense", "world": "reactive", "method": "admm", "zstep": "sqp", "solver": "osqp", "mpc": "interactive",
            "linearize": "last_observed", "mpc.T_p": "20", "mpc.admm.rho": "100", "max_steps": "600", "models_dir": "models",
            "n_jobs": "1", "plots": "False"}
    models = {"cv": {}, "student": {"sha256.student.ckpt": "c" * 64, "model_run.student.ckpt": "d" * 32},
              "surrogate": {"sha256.surrogate.onnx": "e" * 64, "model_run.surrogate.onnx": "f" * 32}}
    for g, courteous, ms in [("cv", 0.25, 3.1), ("student", 0.5, 41.0), ("surrogate", 0.75, 12.5)]:
        log("planner", {**same, **models[g], "gradients": g, "predictor": "student" if g != "cv" else "cv", "seed": "2000000",
                        "episodes": "4", "record_dir": "None"},
            {"episodes": 4, "courteous": courteous, "merged": 1.0, "collision": 0.0, "step_median_ms": ms, "step_p95_ms": 2 * ms})
    log("planner", {**same, **models["student"], "gradients": "student", "predictor": "student", "seed": "5000000",
                    "episodes": "8", "record_dir": "data/small/iterates"},
        {"episodes": 8, "courteous": 0.0, "merged": 0.5, "collision": 0.0, "step_median_ms": 40.0, "step_p95_ms": 80.0})


def figure_of(monkeypatch):
    """The figure compare draws, kept open: [it] once compare ran."""
    import matplotlib.pyplot as plt

    kept = []
    monkeypatch.setattr(plt, "close", kept.append)
    return kept


def test_each_setup_has_a_short_label_inside_the_figure_and_recording_runs_are_no_rows(store, monkeypatch):
    demo_store()
    kept = figure_of(monkeypatch)
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    # the recording run (record_dir: training data for the surrogate) is a data job, no second student row
    assert list(df["label"]) == ["cv/admm/interactive/dense", "student/admm/interactive/dense", "surrogate/admm/interactive/dense"]
    assert list(df["n_episodes"]) == [4, 4, 4]
    (fig,) = kept
    renderer = fig.canvas.get_renderer()
    inside = lambda box, frame: box.x0 >= frame.x0 - 1 and box.x1 <= frame.x1 + 1 and box.y0 >= frame.y0 - 1 and box.y1 <= frame.y1 + 1
    legends = [*fig.legends, *(ax.get_legend() for ax in fig.axes)]
    texts = [fig._suptitle, *(t for lg in legends for t in lg.get_texts()),
             *(t for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label, *ax.texts))]
    assert all(inside(t.get_window_extent(renderer), fig.bbox) for t in texts)  # nothing cut off at the edges
    for ax in fig.axes:
        assert all(inside(t.get_window_extent(renderer), ax.bbox) for t in ax.texts)  # the markers' numbers in their panel
        assert len(ax.containers) == 3
    key = [t.get_text() for t in fig.legends[0].get_texts()]
    assert key == ["1: cv/admm/interactive/dense, 4 ep", "2: student/admm/interactive/dense, 4 ep",
                   "3: surrogate/admm/interactive/dense, 4 ep"]
    assert "seeds 2000000-2000003" in fig._suptitle.get_text()  # what every set-up shares, said once


def test_the_logged_table_starts_with_the_label_and_outcomes_and_says_shared_values_once(store):
    demo_store()
    run(compose_cfg("compare", [f"out_dir={store}"]))
    (r,) = [r for _, r in mlflow.search_runs(experiment_names=["compare"]).iterrows()]
    assert r["tags.mlflow.runName"] == "compare-all-3runs" and r["params.recorded_runs_left_out"] == "1"
    logged = mlflow.artifacts.load_dict(f"runs:/{r['run_id']}/compare_table.json")
    columns, rows = logged["columns"], logged["data"]
    assert columns[:3] == ["label", "courteous_rate", "courteous_lo"] and columns[-1] == "runs"
    assert columns.index("step_median_ms") < columns.index("gradients")  # speed (and accuracy) before the params
    assert all(len({str(row[i]) for row in rows}) > 1 for i in range(len(columns)))  # no column equal in every row
    assert (r["params.every_row.scenario"], r["params.every_row.world"], r["params.every_row.n_episodes"]) == ("dense", "reactive", "4")
    assert r["params.every_row.seed"] == "2000000" and r["params.every_row.zstep"] == "sqp"
    columns_csv = (store / "compare.csv").read_text().splitlines()[0].split(",")
    assert {"scenario", "world", "n_episodes", "label"} <= set(columns_csv)  # compare.csv keeps every column


def test_more_setups_than_a_panel_holds_get_more_panels(store, monkeypatch):
    for T_p in range(8, 16):  # eight set-ups told apart by one param
        log("planner", {"method": "admm", "scenario": "two_lane", "gradients": "cv", "mpc.T_p": str(T_p)},
            {"merged": 1, "courteous": 1, "collision": 0, "step_median_ms": float(T_p), "step_p95_ms": 2.0 * T_p})
    kept = figure_of(monkeypatch)
    df = run(compose_cfg("compare", [f"out_dir={store}"]))
    assert list(df["label"]) == [f"cv/admm/two_lane (mpc.T_p={t})" for t in range(10, 16)] + \
        ["cv/admm/two_lane (mpc.T_p=8)", "cv/admm/two_lane (mpc.T_p=9)"]  # as the params sort: strings
    (fig,) = kept
    assert sorted(len(ax.containers) for ax in fig.axes) == [2, 6]  # one panel of courteous rate per six set-ups
