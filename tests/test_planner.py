"""Planner pieces: ADMM reaches the one-QP MPC optimum, d b_i / d Z from every source, fallbacks instead of crashes."""
import copy
import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate
from scipy import sparse
from test_configs import drift

from bench.branches import ego_controls, execute
from core import jobs
from core.jobs import CONF_DIR, SIGNALS, UserError
from core.rollout import ego_xy
from data import perception
from data.world import backfill
from distill import models as distill_models
from planner import admm, cli, cost, dynamics, mpc, step
from planner import zstep as zsteps
from planner.gradients import Autodiff, CentralDifferences
from planner.qp import QP
from planner.safety import Safety
from planner.setup import build, drive, make, planner_config, setup


def source(gradients, *overrides):
    """The gradient source `planner gradients=...` builds (cv and analytic need no model)."""
    return make("two_lane", [f"gradients={gradients}", *overrides])[1]


@pytest.fixture(scope="module")
def two_lane():
    """The two_lane scenario, cv gradients and the MPC settings, as the planner builds them."""
    return make("two_lane", ["gradients=cv"])


@pytest.fixture(scope="module")
def sqp():
    """The default Z-step (conf/zstep/sqp.yaml, a partial), as conf/solver/admm.yaml binds it to mpc_step."""
    return build(planner_config("two_lane").zstep)


def observe(z, u_prev=(0.0, 0.0)):
    """An observation of states z (M, 4) with a constant-velocity back-filled history."""
    return mpc.Observation(z[0].copy(), np.array(u_prev), backfill(z, 8, 0.2))


def test_admm_converges_to_the_stacked_qp_when_safety_is_inactive(two_lane, sqp):
    scenario, cv, s = two_lane
    z = scenario.make_world(0).z
    z[1:, 0] += 300.0  # the others far ahead: every b_i is slack
    obs = observe(z, (0.05, 0.3))
    prob, solvers, start = mpc.build(s, obs, cv, None, sqp)
    st, solve = admm.admm_solve(prob, solvers, start, max_iters=3000, tol_F=1e-7, tol_step=1e-7)
    assert solve.reason == "converged" and solve.F_norm < 1e-6
    # The same MPC as one QP over x = [Delta; alpha; Z]: J, F = 0, the same boxes.
    dyn, T = prob.dyn, s.T_p
    P = sparse.block_diag([prob.Phi_1.P, prob.Phi_2.P, prob.Phi_3.P], format="csc")
    q = np.concatenate([prob.Phi_1.q, prob.Phi_2.q, prob.Phi_3.q])
    lo, hi = mpc.state_box(s)
    G = sparse.vstack([sparse.csc_matrix(np.hstack([dyn.A, dyn.B, dyn.C])), sparse.eye(6 * T)], format="csc")
    l = np.concatenate([-dyn.D, np.full(T, s.delta_box[0]), np.full(T, s.a_box[0]), lo])
    u = np.concatenate([-dyn.D, np.full(T, s.delta_box[1]), np.full(T, s.a_box[1]), hi])
    x = QP(P, q, G, l, u, {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 100000, "polishing": True}).solve()
    assert np.abs(np.concatenate([st.Delta, st.alpha, st.Z]) - x).max() < 1e-4
    assert abs(prob.J(st) - (0.5 * x @ P @ x + q @ x + prob.Phi_1.r + prob.Phi_2.r + prob.Phi_3.r)) < 1e-5


def sources():
    """(gradients, predictor, tolerance) for every source; trained ones come from the session's tiny models."""
    return [("cv", "auto", 1e-6), ("analytic", "auto", 1e-6), ("fd", "analytic", 1e-4), ("teacher", "analytic", 1e-6),
            ("teacher", "trained", 1e-6), ("student", "trained", 2e-2)]


def trained_source(gradients, models_dir):
    """A trained source; the ReLU teacher in float64, so that central differences can resolve its kinked gradient."""
    if gradients == "student":
        return source("student", f"models_dir={models_dir}")
    module = copy.deepcopy(distill_models.load("teacher", models_dir).module).double()
    return Autodiff("teacher", distill_models.TorchPredictor("teacher", module))


@pytest.mark.parametrize("gradients,predictor,tol", sources())
def test_safety_gradient_matches_central_differences(two_lane, gradients, predictor, tol, request):
    scenario, _, s = two_lane
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # the ego nudging towards the platoon: the analytic predictor reacts
    obs = observe(z)
    if predictor == "trained":
        src = trained_source(gradients, request.getfixturevalue("tiny_models")[0])
    else:
        src = source(gradients, *([f"predictor={predictor}"] if predictor != "auto" else []),
                     *(["gradients.h=1e-4"] if gradients == "fd" else []))
    Z = mpc.simulate(obs.z0, np.full(s.T_p, 0.1), np.full(s.T_p, 0.5), s.params)
    b, Jb, _ = Safety(src, obs.history, s.R, s.T_p).linearize(Z)
    values = Safety(CentralDifferences("fd", src.predictor, 1e-4), obs.history, s.R, s.T_p)
    h = 1e-2 if tol > 1e-3 else 1e-6  # the float32 student needs a larger step
    Jfd = np.stack([(values(Z + h * e) - values(Z - h * e)) / (2 * h) for e in np.eye(len(Z))], 1)
    assert np.abs(Jfd).max() > 1.0  # the constraints do depend on the plan
    if gradients in ("analytic", "teacher", "student"):  # interactive: the others' reaction shows in d b_i / d Z
        direct = np.zeros_like(Jfd)
        ego = ego_xy(Z, s.T_p)
        vals = src.values(obs.history, ego[None])[0]
        for n in range(vals.shape[1] - 1):
            for t in range(s.T_p):
                direct[n * s.T_p + t, 4 * t:4 * t + 2] = 2 * (ego[t] - vals[t, n + 1])
        assert np.abs(Jfd - direct).max() > 1e-3
    assert np.abs(Jb - Jfd).max() <= tol * max(1.0, np.abs(Jfd).max())


def test_nan_observation_falls_back(two_lane, sqp):
    scenario, cv, s = two_lane
    obs = observe(scenario.make_world(0).z)
    bad = obs._replace(history=np.where(np.arange(obs.history.size).reshape(obs.history.shape) == 7, np.nan, obs.history))
    result = step.mpc_step(s, bad, cv, None, sqp)
    assert "non-finite observation" in result.fallback and np.all(np.isfinite(result.u))


def test_daqp_failure_falls_back(two_lane, sqp):
    scenario, cv, s = two_lane
    obs = observe(scenario.make_world(0).z)
    crossed = dataclasses.replace(s)
    object.__setattr__(crossed, "delta_box", (0.1, -0.1))  # past Settings' check, lower above upper: DAQP refuses the box QP
    result = step.mpc_step(crossed, obs, cv, None, sqp)
    assert "solver failure (DAQP exit flag -" in result.fallback and np.all(np.isfinite(result.u))


def test_built_steps_are_plain_partials_that_answer_as_hydras_own(two_lane):
    """core.jobs.build's step and its Z-step: plain partials (the installed Hydra's partial re-checks its target
    policy on every call) of the same functions and arguments as Hydra's own, with the same plan, control and reason."""
    scenario, cv, s = two_lane
    node = planner_config("two_lane").solver.step
    ours, hydras = build(node), instantiate(node, _convert_="all")
    assert type(ours) is functools.partial and type(ours.keywords["zstep"]) is functools.partial
    assert ours.func is hydras.func is step.mpc_step
    assert (ours.keywords["zstep"].func, ours.keywords["zstep"].keywords) == (hydras.keywords["zstep"].func,
                                                                             hydras.keywords["zstep"].keywords)
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # the ego nudging towards the platoon: the safety rows bind
    a, b = (f(s, observe(z), cv, None) for f in (ours, hydras))
    assert a.reason == b.reason and np.array_equal(a.u, b.u)
    assert all(np.array_equal(x, y) for x, y in zip(a.plan[:4], b.plan[:4]))


def test_unknown_names_and_missing_models_are_one_line_errors(tmp_path):
    choices = "choose one of analytic, cv, fd, oracle, student, student_hyp, surrogate, teacher, teacher_hyp"
    with pytest.raises(UserError, match=f"unknown gradients 'bogus'; {choices}"):
        jobs.check_groups(["gradients=bogus"])
    with pytest.raises(UserError, match="unknown zstep 'nope'; choose one of pygranso, sqp"):
        jobs.check_groups(["-m", "zstep=sqp,nope"])  # every value of a sweep
    jobs.check_groups(["gradients=cv,student", "method=both", "seed=3"])
    with pytest.raises(UserError, match="surrogate.onnx not found: run `surrogate`"):
        source("surrogate", "predictor=analytic", f"models_dir={tmp_path}")
    with pytest.raises(UserError, match="distill model=teacher"):
        source("teacher", f"models_dir={tmp_path}")
    with pytest.raises(SystemExit):
        cli.prepare(["planner", "scenario=nowhere"])


def test_gradients_flag_spelling():
    assert cli.translate(["planner", "--gradients=surrogate", "scenario=three_lane"]) == \
        ["planner", "gradients=surrogate", "scenario=three_lane"]
    assert cli.translate(["planner", "--gradients", "fd", "method=nnmpc"]) == ["planner", "gradients=fd", "method=nnmpc"]


def test_linearisation_along_a_simulated_plan_is_exact_there_and_second_order_near_it(two_lane):
    scenario, _, s = two_lane
    rng = np.random.default_rng(0)
    z0 = np.array([9.2, 0.3, 0.05, 5.0])
    Delta, alpha = rng.uniform(-0.3, 0.3, s.T_p), rng.uniform(-2.0, 2.0, s.T_p)
    Z = mpc.simulate(z0, Delta, alpha, s.params)
    dyn = dynamics.linearize(z0, 0.1, -0.5, s.params, s.T_p, (Delta, alpha, Z))
    assert np.abs(dyn.F(Delta, alpha, Z)).max() < 1e-12  # A Delta + B alpha + C Z + D = 0 on the rollout itself
    dD, da = rng.normal(size=s.T_p), rng.normal(size=s.T_p)
    res = [np.abs(dyn.F(Delta + h * dD, alpha + h * da, mpc.simulate(z0, Delta + h * dD, alpha + h * da, s.params))).max()
           for h in (1e-2, 2e-2)]
    assert 1e-9 < res[0] < 1e-2 and 3.0 < res[1] / res[0] < 5.0  # off the plan the error is quadratic in the step
    about_z0 = dynamics.linearize(z0, Delta[0], alpha[0], s.params, s.T_p)  # eq. (5): one linearisation for the horizon
    assert np.abs(about_z0.F(Delta, alpha, Z)[:4]).max() < 1e-12 and np.abs(about_z0.F(Delta, alpha, Z)).max() > 1e-3


def test_cost_blocks_match_the_papers_sums(two_lane):
    _, _, s = two_lane
    w, T, rng = s.weights, s.T_p, np.random.default_rng(1)
    for _ in range(5):
        Delta, alpha, Z = rng.normal(0, 0.3, T), rng.normal(0, 2.0, T), rng.normal(0, 5.0, 4 * T)
        d_prev, a_prev, y_ref, v_ref = rng.normal(0, 0.2), rng.normal(0, 1.0), rng.uniform(0, 8), rng.uniform(2, 8)
        d, a = np.concatenate([[d_prev], Delta]), np.concatenate([[a_prev], alpha])
        Phi_1 = sum(w.lambda_delta * d[k + 1] ** 2 + w.lambda_ddelta * (d[k + 1] - d[k]) ** 2 for k in range(T))
        Phi_2 = sum(w.lambda_a * a[k + 1] ** 2 + w.lambda_da * (a[k + 1] - a[k]) ** 2 for k in range(T))
        Phi_3 = sum(w.lambda_div * (Z[4 * k + 1] - y_ref) ** 2 + w.lambda_v * (Z[4 * k + 3] - v_ref) ** 2 for k in range(T))
        assert cost.Phi_1(T, w, d_prev)(Delta) == pytest.approx(Phi_1, rel=1e-12)
        assert cost.Phi_2(T, w, a_prev)(alpha) == pytest.approx(Phi_2, rel=1e-12)
        assert cost.Phi_3(T, w, y_ref, v_ref)(Z) == pytest.approx(Phi_3, rel=1e-12)


def test_penalty_mode_drives_and_its_z_step_objective_carries_minus_lambda_s_sum_b_i():
    cfg = planner_config("two_lane", ["gradients=analytic", "zstep.settings.mode=penalty", "zstep.settings.lambda_s=2.0",
                                      "world=predictor", "max_steps=3"])
    scenario, src, s = setup(cfg)
    ep = drive(cfg, scenario, src, s, "admm")
    assert len(ep.rows) == 3 and np.isfinite(ep.controls).all() and all(r["iterations"] > 0 for r in ep.rows)
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # nudging towards the platoon: b_i varies with the plan
    prob, solvers, st = mpc.build(s, observe(z), src, None, build(cfg.zstep))
    zstep, rng = solvers.zstep, np.random.default_rng(2)
    mu, c_Z = rng.normal(size=4 * s.T_p), prob.dyn.C @ st.Z + rng.normal(0, 0.1, 4 * s.T_p)
    lin_q = prob.Phi_3.q + prob.dyn.C.T @ (mu - s.admm.rho * c_Z)
    objective = lambda Z: (prob.Phi_3(Z) + mu @ (prob.dyn.C @ Z) + s.admm.rho / 2 * np.sum((prob.dyn.C @ Z - c_Z) ** 2)
                           - 2.0 * zstep.safety(Z).sum())
    Z1, Z2 = st.Z, st.Z + rng.normal(0, 0.3, st.Z.shape)
    merit = lambda Z: zsteps.merit(zstep.data.H, lin_q, Z, zstep.safety(Z), zstep.sqp)
    assert merit(Z1) - merit(Z2) == pytest.approx(objective(Z1) - objective(Z2), rel=1e-9)  # equal up to a constant
    assert abs(zstep.safety(Z1).sum() - zstep.safety(Z2).sum()) > 1e-2  # so the - lambda_s sum b_i term was tested
    Z_new = zsteps.z_update(zstep.kernel(), True, zstep.safety.linearize(st.Z)[2], st.Z, mu, c_Z, 0.0, True, SIGNALS)[0]
    assert objective(Z_new) < objective(st.Z)  # the step descends the penalty-form objective


def group_options(group):
    """The options of a config group (conf/<group>/*.yaml)."""
    return sorted(p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml"))


@pytest.mark.parametrize("override", [f"{g}={o}" for g in ("gradients", "predictor", "zstep", "method") for o in group_options(g)])
def test_every_planner_target_agrees_with_its_code_defaults(override):
    problems, checked, _ = drift(planner_config("two_lane", [override]), f"planner {override}")
    assert checked >= 5 and not problems, "\n".join(problems)


def test_strategy_groups_build_the_named_classes():
    cfg = planner_config("two_lane", ["gradients=fd", "zstep=pygranso", "method=both", "gradients.h=0.05", "predictor=analytic"])
    assert isinstance(build(cfg.gradients), CentralDifferences) and build(cfg.gradients).h == 0.05
    assert build(cfg.gradients).predictor.name == "analytic"
    zstep = build(cfg.solver.step).keywords["zstep"]  # the ADMM step gets the chosen Z-step beside its Settings
    assert zstep.func.name == "pygranso" and zstep.keywords["settings"].maxit == cfg.zstep.settings.maxit
    assert list(cfg.method) == ["admm", "nnmpc"] and build(cfg.method.nnmpc).keywords["lengths"] == [8.0, 12.0, 16.0, 24.0, 32.0]
    assert make("two_lane", ["gradients=cv"])[2].R == pytest.approx(3.95)  # r + r_i + eps from conf/paper/table1.yaml


def test_oracle_replays_the_worlds_own_response_and_leaves_the_world_untouched():
    scenario, oracle, _ = make("two_lane", ["gradients=oracle"])

    def nudge(world, y, steps):
        """execute() of the ego steering to y (m) at constant speed for `steps` in a deep copy of `world`."""
        z0 = world.states()[0]
        return execute(world, ego_controls(z0, np.full(steps, y), z0[3], world.params, k_y=0.6, a_bounds=(0.0, 0.0)))

    world = nudge(scenario.make_world(0), 2.5, 5)[1]  # the ego leaning into the cooperative car's lane
    z, t = world.states(), world.t
    true = np.stack([nudge(world, y, 8)[0] for y in (0.0, 3.0)])  # back off / push on
    seen = perception.observe(world, 4, 8)
    oracle.predictor.world, oracle.predictor.ids = world, seen.ids
    pred = oracle.values(seen.history, true[:, :, 0])
    assert np.abs(pred - true).max() < 1e-6
    assert (true[1] - true[0])[-1, 3, 0] < -0.4  # a real response: the yielder falls back by more than 40 cm
    assert np.array_equal(world.states(), z) and world.t == t


def test_oracle_outside_the_reactive_closed_loop_is_one_line_error():
    oracle = source("oracle")
    with pytest.raises(UserError, match="only the planner's closed loop with world=reactive"):
        oracle.values(np.zeros((8, 5, 2)), np.zeros((1, 8, 2)))
    for pair in (["gradients=teacher", "predictor=oracle"], ["gradients=oracle", "predictor=cv"]):
        with pytest.raises(UserError, match="gradients=oracle and predictor=oracle go only together"):
            make("two_lane", pair)
    cfg = planner_config("two_lane", ["gradients=oracle", "world=predictor"])
    with pytest.raises(UserError, match="gradients=oracle predicts with the world's own drivers; it needs world=reactive"):
        drive(cfg, *setup(cfg), "admm")
