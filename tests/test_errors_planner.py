"""The planner under bad inputs: a bad observation or step error is a reported fallback, never a traceback; a
set-up it cannot drive is one line before the first step; a batch fails on crashes; compare never pools differing
set-ups; the gymnasium policy and env check what they are given."""
import csv
import os
import re
import signal

import mlflow
import numpy as np
import pytest
from errors_common import error_lines
from hydra.utils import instantiate

from conftest import compose_cfg
from core import jobs
from core.jobs import UserError, mlflow_run
from data.world import backfill
from planner import admm, batch, cli, jit_rollout, mpc, safeguard, setup
from planner.compare import run as compare
from planner.setup import planner_config


@pytest.fixture(autouse=True)
def session_store():
    """After each test, MLflow on the session's store again (the `store` fixture's own one ends with its test)."""
    yield
    mlflow.set_tracking_uri(os.environ["MLFLOW_TRACKING_URI"])


@pytest.fixture(scope="module")
def start():
    """two_lane settings, an observation of its start, a warm plan from one solved step (analytic predictor), the ADMM
    and NNMPC steps."""
    cfg = planner_config("two_lane", ["gradients=analytic", "method=nnmpc"])
    scenario, source, s = setup.setup(cfg)
    z = scenario.make_world(0).z
    obs = mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2))
    admm_step = instantiate(cfg.solver.step)
    return s, source, obs, admm_step(s, obs, source, None).plan, admm_step, instantiate(cfg.method.nnmpc)


@pytest.mark.parametrize("field", ["z0", "u_prev", "history"])
@pytest.mark.parametrize("bad", [np.inf, -np.inf, np.nan])
def test_non_finite_observation_is_a_reported_fallback(start, field, bad):
    s, source, obs, warm, admm_step, nnmpc_step = start
    broken = getattr(obs, field).copy()
    broken.flat[1] = bad
    obs = obs._replace(**{field: broken})
    steps = [lambda w: admm_step(s, obs, source, w)]
    if field != "u_prev":  # NNMPC never reads the last input
        steps.append(lambda w: nnmpc_step(s, obs, source, w))
    for step in steps:
        for w in (warm, None):
            result = step(w)
            assert "non-finite observation" in result.fallback
            assert np.all(np.isfinite(result.u)) and result.reason == "fallback"


def test_braking_fallback_stops_the_ego_and_never_reverses(start):
    s, source, obs, *_ = start
    slow = obs._replace(z0=np.array([obs.z0[0], 0.0, 0.0, 0.3]))  # 0.3 m/s: one step of the full brake would reverse
    result = safeguard.fallback(s, slow, source, None, "test")
    assert "braking in lane" in result.fallback
    assert result.u[1] == pytest.approx(-0.3 / s.params.dt) and result.u[1] > mpc.BRAKE
    v = mpc.simulate(slow.z0, result.plan.Delta, result.plan.alpha, s.params)[3::4]
    np.testing.assert_allclose(v, 0.0, atol=1e-12)  # stopped after one step and held there
    fast = safeguard.fallback(s, obs._replace(z0=np.array([obs.z0[0], 0.0, 0.0, 5.0])), source, None, "test")
    assert fast.u[1] == mpc.BRAKE  # far from a stop: the configured deceleration


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
    monkeypatch.setattr(jit_rollout, "predicted", broken)  # the compiled rollout of cv, called from Python
    monkeypatch.setattr(admm, "compiled_solves", broken)  # and the one-call ADMM solves
    for w in (None, warm):
        r = step(s, obs, source, w)
        assert r.reason == "fallback" and r.fallback.startswith("step error (ValueError: matmul: size 80 is different from 30)")
    monkeypatch.setattr(source, "values", broken)  # not even the shifted plan can be judged: braking in lane
    assert step(s, obs, source, warm).fallback.endswith("; braking in lane")


def test_a_one_step_horizon_plans():
    cfg = planner_config("two_lane", ["gradients=cv", "mpc.T_p=1", "max_steps=3", "method=both"])
    scenario, source, s = setup.setup(cfg)
    for m in ("admm", "nnmpc"):
        ep = setup.drive(cfg, scenario, source, s, m)
        assert len(ep.rows) == 3 and np.isfinite(ep.controls).all()


def test_failing_run_is_marked_failed_with_the_error():
    cfg = compose_cfg("planner", ["scenario=two_lane"])
    with pytest.raises(UserError):
        with mlflow_run("hardening", cfg, run_name="boom") as run:
            raise UserError("the planner found nothing to plan")
    got = mlflow.get_run(run.info.run_id)
    assert got.info.status == "FAILED"
    assert got.data.tags["error"] == "UserError: the planner found nothing to plan"


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


def killed_at_7401(cfg_dict, method, seed):
    """batch.episode, but the worker process that drives seed 7401 is killed outright, as the out-of-memory killer ends one."""
    if seed == 7401:
        os.kill(os.getpid(), signal.SIGKILL)
    return batch.episode(cfg_dict, method, seed)


@pytest.mark.slow  # three worker processes import the planner
def test_a_killed_worker_is_its_episodes_crash_and_the_others_are_kept(tmp_path, monkeypatch):
    monkeypatch.setattr(batch, "episode", killed_at_7401)  # what the workers are given to run
    assert cli.run(batch_cfg(tmp_path, 7400, "episodes=4", "n_jobs=2", "tolerate_crashes=true"))["nnmpc"]["crashes"] == 1
    assert runs_of(7400) == ["FINISHED"]
    with open(next(tmp_path.glob("episodes_*.csv"))) as f:
        rows = list(csv.DictReader(f))
    assert [(r["seed"], r["crash"]) for r in rows] == [("7400", "0"), ("7401", "1"), ("7402", "0"), ("7403", "0")]
    assert re.match(r"TerminatedWorkerError: its worker process was killed \(.*SIGKILL", rows[1]["error"]), rows[1]["error"]
    assert sorted(p.name for p in (tmp_path / "steps").iterdir()) == [f"nnmpc_{s}.csv" for s in (7400, 7402, 7403)]


def test_compare_splits_runs_that_differ_in_any_setting_and_pools_the_rest(store):
    cfg = planner_config("two_lane", ["gradients=cv"])
    base = jobs.flatten(cfg) | {"gradients": "cv", "predictor": "cv", "method": "admm", "zstep": "sqp", "solver": "admm",
                                "scenario": "two_lane"}
    ok = {"merged": 1, "collision": 0, "step_median_ms": 5.0, "step_p95_ms": 9.0, "t_merge_s": 2.2, "C_max": 60, "d_min_m": 4.0}
    mlflow.set_experiment("planner")
    # models_dir pools: the sha256 of each model file says which models a run used
    for change in [{}, {"n_jobs": "2", "plots": "False", "out_dir": "/elsewhere", "models_dir": "other"}, {"solver": "ipopt"},
                   {"T_obs": "2"}, {"paper.cost.lambda_v": "7.0"}, {"scenario.merge_tol": "100"},
                   {"sha256.student.ckpt": "b" * 64},
                   {"method.nnmpc.lengths": "[8.0]"}]:  # the last: a method=both run's config of the method it was not
        with mlflow.start_run():
            params = list((base | change).items())
            for i in range(0, len(params), 100):
                mlflow.log_params(dict(params[i : i + 100]))
            mlflow.log_metrics(ok)
    df = compare(compose_cfg("compare", [f"out_dir={store}"]))
    assert len(df) == 6 and sorted(df["n_runs"]) == [1, 1, 1, 1, 1, 3]
    assert set(df.attrs["params"]) >= {"solver", "T_obs", "paper.cost.lambda_v", "scenario.merge_tol", "sha256.student.ckpt"}
    assert "n_jobs" not in df and "method.nnmpc.lengths" not in df
    assert sorted(df["solver"]) == ["admm"] * 5 + ["ipopt"] and sorted(df["T_obs"]) == ["2"] + ["8"] * 5


def test_compare_ignores_only_keys_of_the_planner_config():
    keys = jobs.flatten(planner_config("two_lane"))
    for key in compose_cfg("compare").ignore:
        assert any(k == key or k.startswith(f"{key}.") for k in keys), key


def test_world_predictor_that_cannot_see_every_car_is_refused_before_driving(tmp_path, monkeypatch, capsys):
    from planner import cli

    monkeypatch.setattr("planner.setup.drive", lambda *a, **k: pytest.fail("drove an episode"))
    with pytest.raises(SystemExit) as e:
        cli.run(compose_cfg("planner", ["scenario=dense", "world=predictor", "gradients=cv", f"out_dir={tmp_path}"]))
    assert e.value.code == 2
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith("error: world=predictor moves every car with the predictor, but it sees n_slots=4 of the ")


def test_a_record_dir_that_is_a_file_is_refused_before_driving(tmp_path, monkeypatch, capsys):
    from planner import cli

    (tmp_path / "a_file").write_text("")
    monkeypatch.setattr("planner.setup.drive", lambda *a, **k: pytest.fail("drove an episode"))
    with pytest.raises(SystemExit) as e:
        cli.run(compose_cfg("planner", ["gradients=cv", f"record_dir={tmp_path / 'a_file'}", f"out_dir={tmp_path / 'out'}"]))
    assert e.value.code == 2
    (err,) = error_lines(capsys.readouterr().err)
    assert err.startswith(f"error: cannot write to the output folder {tmp_path / 'a_file'}") and "record_dir=" in err


@pytest.mark.parametrize("override,message", [
    ("mpc.T_p=0", "mpc.T_p=0: must be an integer in [1, 200]"), ("mpc.admm.rho=-5", "mpc.admm.rho=-5: must be"),
    ("mpc.admm.max_iters=0", "mpc.admm.max_iters=0: must be an integer in [1, 10000]"),
    ("scenario.params.dt=0", "scenario.params.dt=0: must be a number > 0"),
])
def test_the_gym_policy_is_built_through_the_commands_checks(override, message):
    from planner.gym_policy import MergePolicy

    with pytest.raises(UserError, match=f"^{re.escape(message)}"):
        MergePolicy(["gradients=cv", override])


@pytest.fixture(scope="module")
def gym_policy():
    """highway-env's dense merge and the planner as its policy (cv), reset."""
    import gymnasium

    from planner.gym_policy import MergePolicy

    env = gymnasium.make("admm-nnmpc/DenseMerge-v0")
    policy = MergePolicy(["gradients=cv"])
    return env, policy


@pytest.mark.parametrize("observation", [np.zeros(6), np.zeros((24, 5)), np.full((24, 6), np.nan), "none"])
def test_the_gym_policy_answers_a_bad_observation_in_one_line(observation, gym_policy):
    _, policy = gym_policy
    policy.reset()
    with pytest.raises(UserError, match=r"^MergePolicy: an observation is rows \[present, id, x, y, heading, speed\]"):
        policy(observation)


@pytest.mark.parametrize("action", [[np.nan, np.nan], np.zeros(5), [0.1], "left", [[0.1, 0.2]]])
def test_the_env_answers_a_bad_action_in_one_line(action, gym_policy):
    env, _ = gym_policy
    env.reset(seed=2000000)
    with pytest.raises(UserError, match=r"takes \[acceleration, steering\], two finite numbers in \[-1, 1\]$"):
        env.step(action)
    env.step([0.0, 0.0])  # a good one still steps
