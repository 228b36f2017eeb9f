"""Closed loop on two_lane (others moved by the predictor, as the paper): the interactive predictor lets ADMM open
the gap and merge; constant velocity cannot; bad starts and bad names are reported, never a traceback."""
import os
import subprocess
import sys

import mlflow
import numpy as np

from conftest import compose_cfg
from planner import cli, closed_loop
from planner.setup import build, planner_config, setup


def plan(tmp_path, *overrides):
    """planner.cli.run on two_lane with the predictor moving the others; returns {method: metrics}."""
    cfg = compose_cfg("planner", ["scenario=two_lane", "world=predictor", f"out_dir={tmp_path}", *overrides])
    return cli.run(cfg)


def test_interactive_predictor_merges_and_reports(tmp_path):
    results = plan(tmp_path, "gradients=analytic", "method=both")
    admm = results["admm"]
    assert admm["merged"] == 1 and admm["collision"] == 0 and admm["t_merge"] < 20
    assert admm["t_merge"] < results["nnmpc"]["t_merge"]
    for name in ("steps_admm.csv", "snapshots_admm.png", "controls_admm_nnmpc.png", "trajectory_cost_admm_nnmpc.png"):
        assert (tmp_path / name).stat().st_size > 0
    runs = mlflow.search_runs(experiment_names=["planner"],  # this run's, not other tests' (a stopped one has no steps)
                              filter_string=f"params.gradients = 'analytic' and params.out_dir = '{tmp_path}'")
    children = runs[runs["tags.mlflow.parentRunId"].notna()]  # under the admm+nnmpc parent run
    assert set(runs["params.method"]) == {"admm", "nnmpc", "admm+nnmpc"} and children["metrics.step_median_ms"].notna().all()
    assert set(children["tags.mlflow.parentRunId"]) == set(runs.loc[runs["params.method"] == "admm+nnmpc", "run_id"])


def test_constant_velocity_cannot_open_the_gap(tmp_path):
    m = plan(tmp_path, "gradients=cv", "plots=false", "linearize=along_plan")["admm"]
    assert m["merged"] == 0 and m["collision"] == 0 and m["steps"] > 20  # drove on beside the platoon to x_ref


def test_start_in_collision_is_reported(tmp_path):
    cfg = planner_config("two_lane", ["gradients=cv"])
    (scenario, source, s), step = setup(cfg), build(cfg.solver.step)
    world = scenario.make_world(0)
    world.z[0, :2] = world.z[2, :2] - [0.5, 1.4]  # overlapping car 2
    ep = closed_loop.drive(world, lambda obs, warm: step(s, obs, source, warm), source, scenario.x_ref,
                           scenario.target_lane, T_obs=8, max_steps=5, others="reactive", n_slots=4)
    assert ep.collided and "start in collision" in ep.notes[0]
    assert any(r["fallback"] for r in ep.rows) and np.isfinite(ep.controls).all()


def test_unknown_gradient_name_is_one_clear_line(tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/m.db"}
    planner = os.path.join(os.path.dirname(sys.executable), "planner")
    out = subprocess.run([planner, "--gradients=bogus", f"out_dir={tmp_path}"], capture_output=True, text=True, env=env,
                         cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip().splitlines() == ["error: unknown gradients 'bogus'; choose one of analytic, cv, fd, oracle, "
                                               "student, student_hyp, surrogate, teacher, teacher_hyp"]


def test_record_dir_keeps_every_state_the_planner_linearises_at(tmp_path):
    """`record_dir` writes one .npz per episode; replaying its states through the source gives back the linearisations
    the step used: the first is taken at the observed history, the ego's planned xy continuing from it."""
    plan(tmp_path, "gradients=cv", "plots=false", "max_steps=3", f"record_dir={tmp_path / 'it'}")
    with np.load(tmp_path / "it" / "two_lane_admm_0.npz") as d:
        history, ego_future = d["history"], d["ego_future"]
    assert history.shape[1:] == (8, 5, 2) and ego_future.shape[1:] == (8, 2) and len(history) == len(ego_future) > 3
    assert np.isfinite(history).all() and np.isfinite(ego_future).all()
    assert np.linalg.norm(ego_future[0, 0] - history[0, -1, 0]) < 5.0  # one step (0.2 s) from the ego's last xy
