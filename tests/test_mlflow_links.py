"""What the MLflow store holds, read back through mlflow.search_runs: a planner run tied to the run that made its model
(by the file's sha256), with that model's accuracy beside its speed, names in one pattern, a few params, a store whose
artifact paths travel with it, and models_dir as a runs:/ URI."""
import os
import re
import sqlite3

import mlflow
import pytest
from errors_common import error_lines
from hydra import compose, initialize_config_dir
from hydra.core.hydra_config import HydraConfig

from conftest import compose_cfg
from core import jobs
from planner import cli
from planner.compare import run as compare

METRIC = re.compile(r"^[a-zA-Z0-9]+(_[a-zA-Z0-9]+)*$")
UNITS = {"t_merge": "t_merge_s", "ttc_min": "ttc_min_s", "b_imposed_max": "b_imposed_max_mps2",
         "step_ms_median": "step_median_ms", "step_ms_p95": "step_p95_ms"}


def plan(tmp_path, models_dir, *overrides):
    cfg = compose_cfg("planner", ["scenario=two_lane", "gradients=student", f"models_dir={models_dir}", "max_steps=3",
                                  "plots=false", f"out_dir={tmp_path}", *overrides])
    return cli.run(cfg)


def runs_of(tmp_path):
    return mlflow.search_runs(experiment_names=["planner"], filter_string=f"params.out_dir = '{tmp_path}'")


@pytest.mark.slow  # trains the tiny models (its own worker's)
def test_a_planner_run_names_its_model_run_and_carries_its_accuracy(tiny_models, tmp_path):
    models_dir = tiny_models[0]
    plan(tmp_path, models_dir, "method=both")
    runs = runs_of(tmp_path)
    assert len(runs) == 3  # the parent and one child per method
    parent = runs[runs["tags.mlflow.parentRunId"].isna()].iloc[0]
    children = runs[runs["tags.mlflow.parentRunId"] == parent["run_id"]]
    assert sorted(children["tags.mlflow.runName"]) == ["admm-student-paper-two_lane-seed0", "nnmpc-student-paper-two_lane-seed0"]
    assert parent["tags.mlflow.runName"] == "admm+nnmpc-student-paper-two_lane-seed0"
    digest = jobs.sha256(models_dir / "student.ckpt")
    made = mlflow.search_runs(experiment_names=["distill"], filter_string=f"tags.`sha256.student.ckpt` = '{digest}'")
    assert len(made) == 1 and made.iloc[0]["params.model"] == "student"
    for _, r in children.iterrows():
        assert r["params.sha256.student.ckpt"] == digest and r["params.model_run.student.ckpt"] == made.iloc[0]["run_id"]
        assert r["metrics.ade_rollout_m"] == pytest.approx(made.iloc[0]["metrics.ade_rollout_m"])  # the student's own
        assert r["metrics.jac_rel_err"] == pytest.approx(made.iloc[0]["metrics.jac_rel_err"])
        assert r["metrics.step_median_ms"] > 0 and r["tags.mlflow.source.git.commit"]
    names = {c[len("metrics."):] for c in runs if c.startswith("metrics.") and runs[c].notna().any()}
    assert all(METRIC.match(n) for n in names) and not names & set(UNITS)  # the unit-less old names are gone
    assert not any(c.endswith("_target_") for c in runs)
    # the models it used, in the model run's MLflow artifacts: models_dir=runs:/<id> plans with the same bytes
    plan(tmp_path / "again", f"runs:/{made.iloc[0]['run_id']}")
    again = runs_of(tmp_path / "again").iloc[0]
    assert again["params.sha256.student.ckpt"] == digest and again["params.models_dir"] == f"runs:/{made.iloc[0]['run_id']}"
    assert [f.path for f in mlflow.artifacts.list_artifacts(run_id=made.iloc[0]["run_id"], artifact_path="models")] == \
        ["models/certificate.json", "models/student.ckpt", "models/student.onnx"]
    logged = mlflow.search_logged_models(experiment_ids=[made.iloc[0]["experiment_id"]], output_format="list",
                                         filter_string=f"source_run_id = '{made.iloc[0]['run_id']}'")
    assert [m.name for m in logged] == ["student"]  # the MLflow model (mlflow.onnx): models_dir=models:/<its id> too
    plan(tmp_path / "by_id", f"models:/{logged[0].model_id}")
    assert runs_of(tmp_path / "by_id").iloc[0]["params.sha256.student.ckpt"] == digest


def test_a_run_recording_iterates_says_so_and_compare_leaves_it_out(store, tmp_path):
    for folder, record in (("eval", "null"), ("record", str(tmp_path / "iterates"))):  # as make demo's MODELS records
        cli.run(compose_cfg("planner", ["scenario=two_lane", "gradients=cv", "max_steps=3", "plots=false",
                                        f"out_dir={tmp_path / folder}", f"record_dir={record}"]))
    runs = mlflow.search_runs(experiment_names=["planner"]).set_index("params.record_dir")
    assert runs.loc["None", "tags.mlflow.runName"] == "admm-cv-paper-two_lane-seed0"
    assert runs.loc[str(tmp_path / "iterates"), "tags.mlflow.runName"] == "admm-cv-paper-two_lane-seed0-record"
    df = compare(compose_cfg("compare", [f"out_dir={tmp_path}"]))
    assert df["runs"].tolist() == [runs.loc["None", "run_id"][:8]] and df["label"].tolist() == ["cv/admm/paper/two_lane"]


def test_dataset_runs_are_named_by_what_they_hold(tiny_dataset):
    d = compose_cfg("make_dataset", ["dataset=tiny"]).dataset
    made = mlflow.search_runs(experiment_names=["dataset"], filter_string=f"params.out_dir = '{tiny_dataset.parent}'")
    assert made["tags.mlflow.runName"].tolist() == [f"tiny-dense-episodes{d.episodes}-seed{d.seed}"]  # not just `tiny`


def test_a_models_uri_with_no_models_is_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        plan(tmp_path, "runs:/0123456789abcdef0123456789abcdef")
    assert e.value.code == 2
    err = error_lines(capsys.readouterr().err)
    assert len(err) == 1 and err[0].startswith("error: models_dir=runs:/0123456789abcdef0123456789abcdef: no model files")


def test_a_hydra_job_logs_its_choices_and_what_the_command_set():
    overrides = ["gradients=cv", "mpc=courteous", "mpc.T_p=12", "seed=3"]
    with initialize_config_dir(config_dir=jobs.CONF_DIR, version_base="1.3"):
        HydraConfig.instance().set_config(compose("planner", overrides, return_hydra_config=True))  # as inside the job
    try:
        params = jobs.logged_params(compose_cfg("planner", overrides))
        told = jobs.command_overrides()
    finally:
        HydraConfig.instance().cfg = None
    assert params["gradients"] == "cv" and params["mpc"] == "courteous" and params["scenario"] == "two_lane"
    assert params["mpc.T_p"] == "12" and params["seed"] == "3"
    assert not any(k.startswith(("mpc.weights", "scenario.", "paper.")) or k.endswith("_target_") for k in params)
    assert len(params) < 40 and told == overrides


def test_a_store_is_created_again_at_a_name_this_process_has_used(tmp_path, monkeypatch):
    # MLflow keeps the store of every URI it opened: the second creation at the same relative name (another folder) once
    # wrote nothing and failed to rename a file that was never made
    for folder in (tmp_path / "a", tmp_path / "b"):
        folder.mkdir()
        monkeypatch.chdir(folder)
        with jobs.store_lock("sqlite:///mlflow.db"):
            jobs.create_store("sqlite:///mlflow.db")
        assert sorted(p.name for p in folder.iterdir()) == ["mlflow.db", "mlflow.db.lock"]
        with sqlite3.connect(folder / "mlflow.db") as con:
            assert con.execute("select count(*) from alembic_version").fetchone() == (1,)


def test_a_new_store_keeps_its_artifacts_beside_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///mlflow.db")
    before = mlflow.get_tracking_uri()
    try:
        jobs.open_experiment("moved")
        jobs.open_experiment("moved")  # as a job does: once before its work, once in mlflow_run
        assert os.environ["MLFLOW_TRACKING_URI"] == "sqlite:///mlflow.db"  # the user's, not MLflow's absolute one
    finally:
        mlflow.set_tracking_uri(before)  # the other tests' store
    with sqlite3.connect(tmp_path / "mlflow.db") as con:
        (location,) = con.execute("SELECT artifact_location FROM experiments WHERE name = 'moved'").fetchone()
    assert location.startswith("mlruns/")  # relative, as the store's own path: the folder can be moved whole
