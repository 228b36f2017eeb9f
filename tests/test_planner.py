"""Planner pieces: ADMM reaches the one-QP MPC optimum, d b_i / d Z from every source, fallbacks instead of crashes."""
import copy

import numpy as np
import osqp
import pytest
from hydra.utils import instantiate
from scipy import sparse

from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import ego_xy
from distill import models as distill_models
from planner import admm, cli, mpc
from planner.closed_loop import backfill
from planner.gradients import Autodiff, CentralDifferences, make_source
from planner.qp import QP
from planner.safety import Safety


@pytest.fixture(scope="module")
def setup():
    """The composed planner config, the two_lane scenario, and its MPC settings."""
    cfg = compose_cfg("planner", ["scenario=two_lane"])
    scenario = instantiate(cfg.scenario, _convert_="all")
    return cfg, scenario, cli.settings(cfg, scenario)


def observe(z, u_prev=(0.0, 0.0)):
    """An observation of states z (M, 4) with a constant-velocity back-filled history."""
    return mpc.Observation(z[0].copy(), np.array(u_prev), backfill(z, 8, 0.2))


def test_admm_converges_to_the_stacked_qp_when_safety_is_inactive(setup):
    cfg, scenario, s = setup
    z = scenario.make_world(0).z
    z[1:, 0] += 300.0  # the others far ahead: every b_i is slack
    obs = observe(z, (0.05, 0.3))
    prob, start = mpc.build(s, obs, make_source("cv"), None)
    st, solve = admm.admm_solve(prob, start, max_iters=3000, tol_F=1e-7, tol_step=1e-7)
    assert solve.reason == "converged" and solve.F_norm < 1e-6
    # The same MPC as one QP over x = [Delta; alpha; Z]: J, F = 0, the same boxes.
    dyn, T = prob.dyn, s.T_p
    P = sparse.block_diag([prob.Phi_1.P, prob.Phi_2.P, prob.Phi_3.P], format="csc")
    q = np.concatenate([prob.Phi_1.q, prob.Phi_2.q, prob.Phi_3.q])
    lo, hi = mpc.state_box(s)
    G = sparse.vstack([sparse.hstack([dyn.A, dyn.B, dyn.C]), sparse.eye(6 * T)], format="csc")
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
        return make_source("student", "auto", models_dir)
    module = copy.deepcopy(distill_models.load("teacher", models_dir).module).double()
    return Autodiff("teacher", distill_models.TorchPredictor("teacher", module))


@pytest.mark.parametrize("gradients,predictor,tol", sources())
def test_safety_gradient_matches_central_differences(setup, gradients, predictor, tol, request):
    cfg, scenario, s = setup
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # the ego nudging towards the platoon: the analytic predictor reacts
    obs = observe(z)
    if predictor == "trained":
        source = trained_source(gradients, request.getfixturevalue("tiny_models")[0])
    else:
        source = make_source(gradients, predictor, "models", fd_step=1e-4)
    Z = mpc.simulate(obs.z0, np.full(s.T_p, 0.1), np.full(s.T_p, 0.5), s.params)
    b, Jb = Safety(source, obs.history, s.R, s.T_p).linearize(Z)
    values = Safety(CentralDifferences("fd", source.predictor, 1e-4), obs.history, s.R, s.T_p)
    h = 1e-2 if tol > 1e-3 else 1e-6  # the float32 student needs a larger step
    Jfd = np.stack([(values(Z + h * e) - values(Z - h * e)) / (2 * h) for e in np.eye(len(Z))], 1)
    assert np.abs(Jfd).max() > 1.0  # the constraints do depend on the plan
    if gradients in ("analytic", "teacher", "student"):  # interactive: the others' reaction shows in d b_i / d Z
        direct = np.zeros_like(Jfd)
        ego = ego_xy(Z, s.T_p)
        vals = source.values(obs.history, ego[None])[0]
        for n in range(vals.shape[1] - 1):
            for t in range(s.T_p):
                direct[n * s.T_p + t, 4 * t:4 * t + 2] = 2 * (ego[t] - vals[t, n + 1])
        assert np.abs(Jfd - direct).max() > 1e-3
    assert np.abs(Jb - Jfd).max() <= tol * max(1.0, np.abs(Jfd).max())


def test_nan_observation_falls_back(setup):
    cfg, scenario, s = setup
    obs = observe(scenario.make_world(0).z)
    bad = obs._replace(history=np.where(np.arange(obs.history.size).reshape(obs.history.shape) == 7, np.nan, obs.history))
    result = mpc.admm_step(s, bad, make_source("cv"), None)
    assert "non-finite observation" in result.fallback and np.all(np.isfinite(result.u))


def test_osqp_failure_falls_back(setup, monkeypatch):
    cfg, scenario, s = setup
    obs = observe(scenario.make_world(0).z)
    real = osqp.OSQP.solve

    def failing(self, *args, **kwargs):
        result = real(self, *args, **kwargs)
        result.info.status = "primal infeasible"
        return result

    monkeypatch.setattr(osqp.OSQP, "solve", failing)
    result = mpc.admm_step(s, obs, make_source("cv"), None)
    assert "solver failure (OSQP primal infeasible)" in result.fallback and np.all(np.isfinite(result.u))


def test_unknown_names_and_missing_models_are_one_line_errors(tmp_path):
    with pytest.raises(UserError, match="unknown gradients 'bogus'"):
        make_source("bogus")
    with pytest.raises(UserError, match="surrogate"):
        make_source("surrogate", "analytic", str(tmp_path))
    with pytest.raises(UserError, match="distill model=teacher"):
        make_source("teacher", "auto", str(tmp_path))
    with pytest.raises(SystemExit):
        cli.prepare(["planner", "scenario=nowhere"])


def test_gradients_flag_spelling():
    assert cli.translate(["planner", "--gradients=surrogate", "scenario=three_lane"]) == \
        ["planner", "gradients=surrogate", "scenario=three_lane"]
    assert cli.translate(["planner", "--gradients", "fd", "method=nnmpc"]) == ["planner", "gradients=fd", "method=nnmpc"]
