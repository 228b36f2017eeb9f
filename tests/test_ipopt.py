"""solver=ipopt, the full-NLP baseline: the student as a CasADi expression equals its numpy forward pass; on a convex
instance IPOPT and OSQP solve the same QP; with active safety IPOPT's plan satisfies the linear dynamics and b_i >= 0
on core.rollout's numpy rollout of the same predictor; a closed loop logs param `solver`; what it cannot take, and a
missing CasADi, are one clear error line."""
import sys

import mlflow
import numpy as np
import osqp
import pytest
import torch
from scipy import sparse

from conftest import compose_cfg
from core.jobs import UserError
from core.rollout import b_i, ego_xy, rollout
from data.world import backfill
from distill.models import StudentPredictor, TorchPredictor
from distill.student import GeluStudent
from planner import cli, mpc, safeguard
from planner.gradients import ExactLocal
from planner.setup import build, make, planner_config

ca = pytest.importorskip("casadi")
from planner.ipopt import expression, import_casadi, ipopt_step, student_phi  # noqa: E402


@pytest.fixture(scope="module")
def options():
    """IPOPT's options as conf/solver/ipopt.yaml sets them."""
    return build(planner_config("two_lane", ["solver=ipopt"]).solver.step).keywords["options"]


@pytest.fixture(scope="module")
def student():
    """A GELU student with random weights whose acceleration head matters (not the near-CV initialisation)."""
    torch.manual_seed(0)
    net = GeluStudent([16, 16], [0.5, 0.25], 10.0, 0.5, 0.05)
    torch.nn.init.normal_(net.layers[-1].weight, std=0.3)
    return StudentPredictor(net.double())


def observation(scenario, shift_others=0.0):
    """two_lane's start with the ego nudged towards the platoon (y 1.6 m, heading 0.15 rad); others moved by shift_others m."""
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15
    z[1:, 0] += shift_others
    return mpc.Observation(z[0].copy(), np.array([0.05, 0.3]), backfill(z, 8, 0.2))


def test_student_expression_equals_its_numpy_forward(student):
    x = ca.SX.sym("w", 80)
    window = np.array([x[k] for k in range(80)], dtype=object).reshape(1, 8, 5, 2)
    f = ca.Function("phi", [x], [ca.vertcat(*student_phi(student.weights, student.s)(window).reshape(-1))])
    windows = np.random.default_rng(0).normal(scale=5.0, size=(5, 8, 5, 2))
    for w in windows:
        got = np.asarray(f(w.reshape(-1))).reshape(5, 2)
        want = student.phi(w[None])[0]
        assert np.abs(got - want).max() < 1e-10 and np.abs(want[1:] - (2 * w[-1, 1:] - w[-2, 1:])).max() > 1e-3


def test_convex_instance_ipopt_and_osqp_agree(options):
    scenario, source, s = make("two_lane", ["gradients=cv"])
    obs = observation(scenario, shift_others=300.0)  # the others far ahead: no b_i active, a QP
    r = ipopt_step(s, obs, source, None, options)
    assert not r.fallback
    start, dyn = mpc.start_point(s, obs, None)
    Phi = mpc.costs(s, obs.u_prev)
    lo, hi = mpc.state_box(s)
    n = s.T_p
    G = sparse.vstack([sparse.csc_matrix(np.hstack([dyn.A, dyn.B, dyn.C])), sparse.eye(6 * n)], format="csc")
    qp = osqp.OSQP()
    qp.setup(sparse.triu(sparse.block_diag([p.P for p in Phi]), format="csc"), np.concatenate([p.q for p in Phi]), G,
             np.concatenate([-dyn.D, np.full(n, s.delta_box[0]), np.full(n, s.a_box[0]), lo]),
             np.concatenate([-dyn.D, np.full(n, s.delta_box[1]), np.full(n, s.a_box[1]), hi]),
             verbose=False, eps_abs=1e-10, eps_rel=1e-10, max_iter=200000, polishing=True)
    x = qp.solve().x
    J_osqp = mpc.J_of(s, obs.u_prev, x[:n], x[n:2 * n], x[2 * n:])
    ours = np.concatenate([r.plan.Delta, r.plan.alpha, r.plan.Z])
    assert r.b_min > 10.0  # safety far from active
    assert abs(r.J - J_osqp) <= 1e-6 * abs(J_osqp) and np.abs(ours - x).max() < 1e-4
    assert abs(r.J - mpc.J_of(s, obs.u_prev, *np.split(ours, [n, 2 * n]))) < 1e-9  # J is planner.cost's J of the plan


@pytest.mark.parametrize("predictor", ["analytic", "student"])
def test_plan_meets_dynamics_and_safety_on_the_numpy_rollout(options, student, predictor, monkeypatch):
    # the check of the nonlinear bicycle's rollout off: this tests the NLP's own solution, not the linearisation
    monkeypatch.setattr(safeguard, "CHECK_TOL", 100.0)
    scenario, analytic, s = make("two_lane", ["gradients=analytic"])
    source = analytic if predictor == "analytic" else ExactLocal(predictor, student)
    obs = observation(scenario)
    r = ipopt_step(s, obs, source, None, options)
    assert not r.fallback and r.reason == "Solve_Succeeded"
    _, dyn = mpc.start_point(s, obs, None)
    assert np.abs(dyn.F(r.plan.Delta, r.plan.alpha, r.plan.Z)).max() <= 1e-6
    values = rollout(source.predictor.phi, obs.history[None], ego_xy(r.plan.Z, s.T_p)[None])[0]
    b = b_i(values, s.R)
    assert b.min() >= -1e-6 and np.sum(np.abs(b) < 1e-3) >= 1  # feasible with a safety constraint active
    lo, hi = mpc.state_box(s)
    assert np.all(r.plan.Z >= lo - 1e-6) and np.all(r.plan.Z <= hi + 1e-6)
    assert np.all(np.abs(r.plan.Delta) <= s.delta_box[1] + 1e-6)


def test_sources_without_an_expression_are_one_clear_error():
    with pytest.raises(UserError, match=r"gradients=fd supplies its own derivatives"):
        expression(build(planner_config("two_lane", ["gradients=fd", "predictor=analytic"]).gradients))
    with pytest.raises(UserError, match=r"teacher predictor .* l4casadi"):
        expression(ExactLocal("teacher", TorchPredictor("teacher", torch.nn.Linear(2, 2))))


def test_closed_loop_logs_solver_and_bad_source_is_one_line(tmp_path, capsys):
    cfg = compose_cfg("planner", ["scenario=two_lane", "solver=ipopt", "gradients=analytic", "max_steps=3", "plots=false",
                                  f"out_dir={tmp_path}"])
    assert cli.run(cfg)["admm"]["steps"] == 3
    rows = (tmp_path / "steps_admm.csv").read_text().splitlines()
    assert len(rows) == 4 and all("Solve_Succeeded" in row for row in rows[1:])
    runs = mlflow.search_runs(experiment_names=["planner"], filter_string="params.solver = 'ipopt'")
    assert len(runs) == 1 and runs["params.gradients"][0] == "analytic"
    cfg = compose_cfg("planner", ["scenario=two_lane", "solver=ipopt", "gradients=fd", "predictor=analytic", "max_steps=1",
                                  "plots=false", f"out_dir={tmp_path}"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        cli.run(cfg)
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: solver=ipopt differentiates") and "gradients=fd" in err[0]


def test_missing_casadi_is_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "casadi", None)  # what an environment without the extra looks like to import
    with pytest.raises(UserError, match=r"solver=ipopt needs CasADi.*pip install -e '\.\[ipopt\]'"):
        import_casadi()
