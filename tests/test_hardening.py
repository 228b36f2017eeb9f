"""Bad inputs give one clear error or a reported fallback, never a traceback or lost data. Covered elsewhere:
missing dataset/model naming the command (test_dataset, test_distill_jobs, test_surrogate, test_planner), corrupt
.npz (test_dataset), .ckpt/.onnx (test_distill_jobs, test_surrogate), wrong-shape ONNX (test_surrogate), NaN history
(test_planner), start in collision (test_planner_loop), unknown scenario/gradients (test_planner, test_planner_loop,
test_dataset), resume from a checkpoint (test_distill_jobs)."""
import mlflow
import numpy as np
import pytest
from hydra.utils import instantiate

from conftest import compose_cfg
from core.jobs import UserError, guarded, mlflow_run
from data.world import backfill
from planner import cli, mpc
from planner.setup import make, planner_config, setup


@pytest.fixture(scope="module")
def start():
    """two_lane settings, an observation of its start, a warm plan from one solved step (analytic predictor), the ADMM
    and NNMPC steps."""
    cfg = planner_config("two_lane", ["gradients=analytic", "method=nnmpc"])
    scenario, source, s = setup(cfg)
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


def test_unwritable_output_folder_is_one_line_and_writes_nothing(tmp_path, capsys):
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    before = len(mlflow.search_runs(experiment_names=["planner"]))
    capsys.readouterr()  # MLflow's own set-up lines, if the store is new
    cfg = compose_cfg("planner", ["scenario=two_lane", "gradients=cv", f"out_dir={blocker}/out", "max_steps=2"])
    with pytest.raises(SystemExit) as e:
        cli.run(cfg)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: cannot write to the output folder") and "a_file" in err[0]
    assert [p.name for p in tmp_path.iterdir()] == ["a_file"]
    assert len(mlflow.search_runs(experiment_names=["planner"])) == before  # no run was started


def test_failing_run_is_marked_failed_with_the_error():
    cfg = compose_cfg("planner", ["scenario=two_lane"])
    with pytest.raises(UserError):
        with mlflow_run("hardening", cfg, run_name="boom") as run:
            raise UserError("the planner found nothing to plan")
    got = mlflow.get_run(run.info.run_id)
    assert got.info.status == "FAILED"
    assert got.data.tags["error"] == "UserError: the planner found nothing to plan"


@pytest.mark.parametrize("job,overrides", [
    ("make_dataset", ["dataset=tiny", "out_dir={blocked}"]),
    ("distill", ["model=teacher", "dataset_dir={data}", "models_dir={blocked}", "run_dir={tmp}/run"]),
    ("surrogate", ["dataset_dir={data}", "models_dir={blocked}"]),
])
def test_every_job_refuses_an_unwritable_output_folder_in_one_line(job, overrides, tmp_path, tiny_dataset, capsys):
    from data.cli import run as make_dataset
    from distill.train import run as distill
    from surrogate.cli import run as surrogate

    blocker = tmp_path / "a_file"
    blocker.write_text("")
    fill = dict(blocked=f"{blocker}/out", data=tiny_dataset, tmp=tmp_path)
    cfg = compose_cfg(job, [o.format(**fill) for o in overrides])
    run = {"make_dataset": make_dataset, "distill": guarded(distill), "surrogate": surrogate}[job]  # as the entry points call them
    with pytest.raises(SystemExit) as e:
        run(cfg)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: cannot write to the output folder") and "a_file" in err[-1]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_braking_fallback_stops_the_ego_and_never_reverses(start):
    s, source, obs, *_ = start
    slow = obs._replace(z0=np.array([obs.z0[0], 0.0, 0.0, 0.3]))  # 0.3 m/s: one step of the full brake would reverse
    result = mpc.fallback(s, slow, source, None, "test")
    assert "braking in lane" in result.fallback
    assert result.u[1] == pytest.approx(-0.3 / s.params.dt) and result.u[1] > s.brake
    v = mpc.simulate(slow.z0, result.plan.Delta, result.plan.alpha, s.params)[3::4]
    np.testing.assert_allclose(v, 0.0, atol=1e-12)  # stopped after one step and held there
    fast = mpc.fallback(s, obs._replace(z0=np.array([obs.z0[0], 0.0, 0.0, 5.0])), source, None, "test")
    assert fast.u[1] == s.brake  # far from a stop: the configured deceleration


@pytest.mark.parametrize("relative", [False, True])
def test_beside_a_car_a_plan_no_worse_than_braking_is_acceptable_only_with_check_relative(relative):
    _, source, s = make("two_lane", ["gradients=cv", f"mpc.check_relative={relative}"])
    z0 = np.array([0.0, 1.0, 0.0, 5.0])  # straddling towards the target lane, 3 m from a car beside it at 5 m/s
    cars = np.array([[0.0, 4.0], [60.0, 4.0], [80.0, 4.0], [100.0, 4.0]])
    history = np.stack([np.vstack([z0[:2], cars]) - [5.0 * 0.2 * k, 0.0] for k in range(7, -1, -1)])
    obs = mpc.Observation(z0, np.zeros(2), history)
    Delta, alpha = mpc.brake_plan(s, z0)
    b_brake = mpc.plan_safe(s, obs, source, Delta, alpha)[0]
    assert 3.0**2 - s.R**2 <= b_brake < -1.0  # braking back to the lane centre stays inside R for the checked steps too
    keep = mpc.plan_safe(s, obs, source, Delta, np.zeros(s.T_p))[0]  # the same steering at 5 m/s, still beside it
    towards = mpc.plan_safe(s, obs, source, np.full(s.T_p, 0.3), np.zeros(s.T_p))[0]  # steer at it
    assert b_brake - s.check_tol <= keep < -s.check_tol and towards < b_brake - s.check_tol
    assert mpc.acceptable(s, obs, source, keep) == relative
    assert not mpc.acceptable(s, obs, source, towards)
    assert mpc.acceptable(s, obs, source, -s.check_tol)  # within the tolerance: always
