"""The reliability probe's cases (issue 25): each is one clear line and a non-zero exit, or works; nothing outside the
requested output is written or removed; a store survives a kill while it is created; a batch opens its run first and
fails on crashes; compare never pools set-ups that differ; MLflow is checked before the work."""
import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import numpy as np
import pytest
from hydra.utils import instantiate

from bench import interaction
from conftest import compose_cfg
from core import jobs, validate
from core.jobs import UserError, guarded, mlflow_run
from data.world import backfill
from distill.models import StudentPredictor, TorchPredictor
from distill.train import make_trainer
from planner import cli, jit_admm, jit_rollout, mpc, setup
from planner.compare import run as compare
from planner.setup import check_window, planner_config

BIN = Path(sys.executable).parent  # the venv's console scripts


def job(args, cwd, env=None, timeout=120, **kwargs):
    """Run a console script of the venv in `cwd` (its MLflow store in `env`); returns the CompletedProcess."""
    return subprocess.run([str(BIN / args[0]), *args[1:]], cwd=cwd, env={**os.environ, **(env or {})}, capture_output=True,
                          text=True, timeout=timeout, **kwargs)


def error_lines(stderr: str) -> list[str]:
    """stderr without the log records of MLflow and Hydra (lines that start with their time stamps)."""
    return [s for s in stderr.splitlines() if s.strip() and not re.match(r"^(\d{4}/\d\d/\d\d |\[\d{4}-)", s)]


# 1. a dataset name is one folder name: nothing outside out_dir/<name> is replaced
@pytest.mark.parametrize("name", [".", "..", "../../etc", "a/b", ""])
def test_a_dataset_name_that_is_not_one_folder_is_refused_and_nothing_is_removed(name, tmp_path, capsys):
    from data.cli import run

    (tmp_path / "keep.txt").write_text("mine")
    with pytest.raises(SystemExit) as e:
        run(compose_cfg("make_dataset", [f"out_dir={tmp_path}", f"dataset.name='{name}'", "dataset=tiny", "plot_episodes=0"]))
    assert e.value.code == 2
    assert capsys.readouterr().err.startswith(f"error: dataset.name={name}: must be")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    with pytest.raises(UserError, match="^dataset.name=.*single folder name"):
        validate.check(compose_cfg("distill", [f"dataset.name='{name}'"]), "distill")


# 2. a store killed while MLflow creates its tables is no store at all, and the next job makes a whole one
def test_a_job_killed_while_creating_the_store_leaves_it_usable(tmp_path):
    db = tmp_path / "new.db"
    env = {"MLFLOW_TRACKING_URI": f"sqlite:///{db}"}
    first = subprocess.Popen([str(BIN / "compare"), f"out_dir={tmp_path}"], cwd=tmp_path, env={**os.environ, **env},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while not (db.exists() or db.with_name(".new.db.creating").exists()) and first.poll() is None and time.time() < deadline:
        time.sleep(0.02)
    time.sleep(0.5)  # MLflow's migrations take seconds: well inside them
    first.kill()  # SIGKILL: no clean-up of any kind runs
    first.wait()
    second = job(["compare", f"out_dir={tmp_path}"], tmp_path, env)
    assert second.returncode == 2, second.stderr
    assert error_lines(second.stderr) == ["error: no finished planner runs in the MLflow store: run `planner` first"]
    with sqlite3.connect(db) as con:
        assert con.execute("select count(*) from alembic_version").fetchone() == (1,)


# 3. the planner refuses what its model cannot take; T_p = 1 works; mpc_step falls back on any remaining error
def test_a_window_the_model_cannot_take_is_refused_before_planning():
    net = instantiate(compose_cfg("distill", ["model=student"]).model.net)
    student = StudentPredictor(net)
    assert student.window == (8, 5)  # from its feature map P (78 x 80) and its head
    for over in ("T_obs=3", "T_obs=9", "n_slots=3"):
        with pytest.raises(UserError, match=r"^T_obs=\d+, n_slots=\d: the student model takes windows of T_obs=8 and n_slots=4"):
            check_window(planner_config("two_lane", [over]), student)
    check_window(planner_config("two_lane"), student)  # the default fits
    teacher = instantiate(compose_cfg("distill", ["model=teacher"]).model.net)
    check_window(planner_config("two_lane", ["T_obs=5"]), TorchPredictor("teacher", teacher))  # a GRU reads any T_obs
    with pytest.raises(UserError, match="teacher model takes windows of any T_obs and n_slots=4"):
        check_window(planner_config("two_lane", ["n_slots=5"]), TorchPredictor("teacher", teacher))


def test_a_one_step_horizon_plans():
    cfg = planner_config("two_lane", ["gradients=cv", "mpc.T_p=1", "max_steps=3", "method=both"])
    scenario, source, s = setup.setup(cfg)
    for m in ("admm", "nnmpc"):
        ep = setup.drive(cfg, scenario, source, s, m)
        assert len(ep.rows) == 3 and np.isfinite(ep.controls).all()


def test_an_unexpected_error_in_a_step_is_a_fallback_with_its_reason(monkeypatch):
    cfg = planner_config("two_lane", ["gradients=cv"])
    scenario, source, s = setup.setup(cfg)
    z = scenario.make_world(0).z
    obs = mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2))
    step = instantiate(cfg.solver.step)
    warm = step(s, obs, source, None).plan

    def broken(*args):
        raise ValueError("matmul: size 80 is different from 30")

    monkeypatch.setattr(source, "jacobian", broken)
    monkeypatch.setattr(jit_rollout, "predicted", broken)  # the compiled core's own rollout of cv (mpc.core=compiled)
    monkeypatch.setattr(jit_admm, "admm_loop", broken)  # and its one-call ADMM solve
    for w in (None, warm):
        r = step(s, obs, source, w)
        assert r.reason == "fallback" and r.fallback.startswith("step error (ValueError: matmul: size 80 is different from 30)")
    monkeypatch.setattr(source, "values", broken)  # not even the shifted plan can be judged: braking in lane
    assert step(s, obs, source, warm).fallback.endswith("; braking in lane")


# 4. a corrupt certificate is one line
@pytest.mark.parametrize("text,why", [
    ("{not json", "is not a readable certificate .JSONDecodeError"),
    ("[1, 2]", "has no `scenarios` object"),
    (json.dumps({"scenarios": {"two_lane": {}}}), "certified rho for two_lane .* is None, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": {"rho_bound": "big"}}}), "is big, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": {"rho_bound": -5.0}}}), "is -5.0, not a usable penalty"),
    (json.dumps({"scenarios": {"two_lane": [3]}}), "is None, not a usable penalty"),
])
def test_a_corrupt_certificate_is_one_line(text, why, tmp_path):
    (tmp_path / "certificate.json").write_text(text)
    cfg = planner_config("two_lane", ["gradients=cv", "mpc.rho=certified", f"models_dir={tmp_path}"])
    with pytest.raises(UserError, match=rf"^mpc.rho=certified: .*{why}"):
        setup.setup(cfg)


# 5 and 7. a batch opens its run first, fails on crashes, ends KILLED when stopped
def batch_cfg(tmp_path, seed, *overrides):
    """A tiny random-scenario NNMPC batch of 2 episodes from `seed` (its runs found by that seed)."""
    return compose_cfg("planner", ["scenario=random", "gradients=analytic", "method=nnmpc", "max_steps=4", "episodes=2",
                                   "n_jobs=1", f"seed={seed}", f"out_dir={tmp_path}", *overrides])


def runs_of(seed):
    """Status of the planner runs of `seed`."""
    return list(mlflow.search_runs(experiment_names=["planner"], filter_string=f"params.seed = '{seed}'")["status"])


@pytest.mark.parametrize("crash_seeds,tolerate,fails", [
    ({7000, 7001}, "false", True), ({7100, 7101}, "true", True), ({7200}, "false", True), ({7300}, "true", False)])
def test_a_batch_with_crashes_fails_with_the_count_unless_tolerated(crash_seeds, tolerate, fails, tmp_path, monkeypatch,
                                                                    capsys):
    real = setup.drive

    def flaky(cfg, scenario, source, s, method, seed=None):
        if seed in crash_seeds:
            raise RuntimeError(f"boom {seed}")
        return real(cfg, scenario, source, s, method, seed=seed)

    monkeypatch.setattr(setup, "drive", flaky)
    seed = min(crash_seeds)
    cfg = batch_cfg(tmp_path, seed, f"tolerate_crashes={tolerate}")
    if not fails:
        assert cli.run(cfg)["nnmpc"]["crashes"] == 1 and runs_of(seed) == ["FINISHED"]
        return
    with pytest.raises(SystemExit) as e:
        cli.run(cfg)
    assert e.value.code == 2 and runs_of(seed) == ["FAILED"]
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith(f"error: {len(crash_seeds)} of 2 nnmpc episodes crashed (first: RuntimeError: boom {seed}); see ")
    assert ("tolerate_crashes=true" in err) == (len(crash_seeds) == 1)


def test_sigint_in_a_batch_is_one_line_exit_130_and_its_run_killed(tmp_path):
    db = tmp_path / "m.db"
    proc = subprocess.Popen([str(BIN / "planner"), "scenario=random", "gradients=analytic", "method=nnmpc", "episodes=500",
                             "n_jobs=1", "max_steps=8", f"out_dir={tmp_path}"], cwd=tmp_path,
                            env={**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{db}"}, stderr=subprocess.PIPE, text=True)
    deadline, status = time.time() + 90, []
    while not status and proc.poll() is None and time.time() < deadline:  # its run is open before the first episode
        time.sleep(0.2)
        if db.exists():
            with sqlite3.connect(db) as con:
                try:
                    status = con.execute("select status from runs").fetchall()
                except sqlite3.OperationalError:  # tables not there yet
                    pass
    assert status == [("RUNNING",)]
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and error_lines(err) == ["error: stopped by SIGINT"], err
    with sqlite3.connect(db) as con:
        assert con.execute("select status from runs").fetchall() == [("KILLED",)]


def test_sigint_inside_a_job_ends_its_run_killed():
    def body():
        with mlflow_run("reliability", compose_cfg("compare")) as run:
            body.run_id = run.info.run_id
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)

    with pytest.raises(SystemExit) as e:
        guarded(body)()
    assert e.value.code == 130 and mlflow.get_run(body.run_id).info.status == "KILLED"


# 6. compare pools only runs whose every outcome-changing param is equal
def test_compare_splits_runs_that_differ_in_any_setting_and_pools_the_rest(store):
    cfg = planner_config("two_lane", ["gradients=cv"])
    base = jobs.flatten(cfg) | {"gradients": "cv", "predictor": "cv", "method": "admm", "zstep": "sqp", "solver": "admm",
                                "scenario": "two_lane"}
    ok = {"merged": 1, "collision": 0, "step_ms_median": 5.0, "step_ms_p95": 9.0, "t_merge": 11, "C_max": 60, "d_min_m": 4.0}
    mlflow.set_experiment("planner")
    for change in [{}, {"n_jobs": "2", "plots": "False", "out_dir": "/elsewhere"}, {"solver": "ipopt"}, {"T_obs": "2"},
                   {"mpc.weights.lambda_v": "7.0"}, {"scenario.merge_tol": "100"}, {"models_dir": "other"},
                   {"method.nnmpc.lengths": "[8.0]"}]:  # the last: a method=both run's config of the method it was not
        with mlflow.start_run():
            params = list((base | change).items())
            for i in range(0, len(params), 100):
                mlflow.log_params(dict(params[i : i + 100]))
            mlflow.log_metrics(ok)
    df = compare(compose_cfg("compare", [f"out_dir={store}"]))
    assert len(df) == 6 and sorted(df["n_runs"]) == [1, 1, 1, 1, 1, 3]
    assert set(df.attrs["params"]) >= {"solver", "T_obs", "mpc.weights.lambda_v", "scenario.merge_tol", "models_dir"}
    assert "n_jobs" not in df and "method.nnmpc.lengths" not in df
    assert sorted(df["solver"]) == ["admm"] * 5 + ["ipopt"] and sorted(df["T_obs"]) == ["2"] + ["8"] * 5


def test_compare_ignores_only_keys_of_the_planner_config():
    keys = jobs.flatten(planner_config("two_lane"))
    for key in compose_cfg("compare").ignore:
        assert any(k == key or k.startswith(f"{key}.") for k in keys), key


# 8. an unusable MLflow store is one line before any work
@pytest.mark.parametrize("uri,why", [("sqlite:////proc/no/such/mlflow.db", "cannot use the MLflow store sqlite:////proc"),
                                     ("http://127.0.0.1:9", "cannot use the MLflow store http://127.0.0.1:9")])
def test_an_unusable_store_is_one_line_before_the_work(uri, why, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setattr(setup, "drive", lambda *a, **k: pytest.fail("drove an episode"))
    previous = mlflow.get_tracking_uri()
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        cli.run(compose_cfg("planner", ["gradients=cv", f"out_dir={tmp_path}"]))
    mlflow.set_tracking_uri(previous)  # the tests after this one keep their store
    assert e.value.code == 2 and time.perf_counter() - t0 < jobs.STORE_TIMEOUT_S + 5
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith(f"error: {why}")
    assert os.environ.get("MLFLOW_HTTP_REQUEST_MAX_RETRIES") is None  # the quick check's settings are its own


# 9 and 10. config checks, misspelt keys, empty folders, progress bars
def test_interaction_values_are_checked():  # the bench's values: test_robustness's table of bad config values
    with pytest.raises(UserError) as e:
        validate.check(compose_cfg("evaluate_interaction", ["sources=[]"]), interaction.SCHEMA)
    assert str(e.value).startswith("sources=[]: must be a list of at least 1")


@pytest.mark.parametrize("config,override,message", [
    ("distill", "modle.epochs=3", "Could not override 'modle.epochs'. Key 'modle' is not in struct."),
    ("make_dataset", "dataset.nme=x", "Could not override 'dataset.nme'. Key 'nme' is not in struct."),
    ("results", "bootstrap.resample=3", "Could not override 'bootstrap.resample'. Key 'resample' is not in struct."),
    ("distill", "model=studnet", "unknown model 'studnet'; choose one of student, student_certifiable, student_wide, teacher"),
])
def test_a_misspelt_key_or_option_is_one_line(config, override, message):
    with pytest.raises(UserError) as e:
        jobs.check_overrides(config, [override])
    assert str(e.value) == message
    jobs.check_overrides("distill", ["--help", "modle.epochs=3"])  # with Hydra's own flags the keys are left to Hydra


def test_a_rejected_command_writes_nothing(tmp_path):
    for args in (["distill", "modle.epochs=3"], ["evaluate-interaction", "sources=[]"]):  # before Hydra, inside its job
        r = job(args, tmp_path)
        assert r.returncode == 2 and len(error_lines(r.stderr)) == 1, r.stderr
    assert list(tmp_path.iterdir()) == []


def test_a_redirected_trainer_draws_no_progress_bar(monkeypatch):
    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)
    assert make_trainer(compose_cfg("distill").trainer, logger=False).progress_bar_callback is None
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)
    monkeypatch.delenv("CI", raising=False)
    assert make_trainer(compose_cfg("distill").trainer, logger=False).progress_bar_callback is not None
