"""The MPC step's fast paths give the slow paths' plans: closed-form box QPs, reused linearisations, OSQP at ADMM's
tolerances, the rollout-level surrogate export, residual balancing's dual residual and rho updates (speed: `make bench`)."""
import copy

import numpy as np
import pytest
import torch
from scipy import sparse
from test_surrogate import smooth_student

from bench.states import collect
from core.jobs import UserError
from core.rollout import SLOTS, T_OBS, chain_rule, ego_xy, rollout_jacobian
from planner import admm, mpc
from planner.gradients import Surrogate
from planner.qp import QP, BoxQP, SolverFailure
from planner.safety import Safety
from planner.setup import make
from surrogate import models
from surrogate.export import export, export_rollout
from surrogate.network import Fused, JacobianNet, Rollout

SLOW = ["mpc.box_qp=osqp", "zstep.settings.reuse_radius=0", "zstep.settings.max_iters=2", "mpc.osqp.eps_abs=1e-6", "mpc.osqp.eps_rel=1e-6",
        "~mpc.osqp.adaptive_rho_interval"]  # the reference: OSQP everywhere, tight, two SQP steps each from a fresh linearisation


@pytest.fixture(scope="module")
def states():
    """Planning states (observation, warm start) of a closed-loop two_lane run with the analytic predictor."""
    return collect(scenarios=("two_lane",), per_scenario=8, gradients="analytic")


@pytest.fixture(scope="module")
def analytic():
    """(scenario, analytic source, default settings) of two_lane."""
    return make("two_lane", ["gradients=analytic"])


def test_fast_step_gives_the_slow_plan(states, analytic):
    _, src, fast = analytic
    slow = make("two_lane", ["gradients=analytic", *SLOW])[2]
    both = 0
    for st in states:
        a, b = mpc.mpc_step(fast, st.obs, src, st.warm), mpc.mpc_step(slow, st.obs, src, st.warm)
        assert bool(a.fallback) == bool(b.fallback)
        if a.reason == b.reason == "converged":  # the same fixed point to a few times ADMM's tol_step (1e-3)
            both += 1
            assert np.abs(a.u - b.u).max() <= 5e-3 and np.abs(a.plan.Z - b.plan.Z).max() <= 1e-2
    assert both >= 3


def test_box_qp_closed_form_equals_osqp_inside_and_on_the_box(states, analytic):
    _, src, s = analytic
    prob, _ = mpc.build(s, states[2].obs, src, states[2].warm)
    P = (prob.Phi_1.P + s.rho * prob.dyn.A.T @ prob.dyn.A).toarray()
    tight = {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 100000, "polishing": True}
    rng = np.random.default_rng(0)
    for scale in (0.01, 300.0):  # unconstrained minimiser inside the box, then mostly outside it
        q = scale * rng.normal(size=len(P))
        fast, slow = BoxQP(P, q, -0.5, 0.5, tight, True), BoxQP(P, q, -0.5, 0.5, tight, False)
        x = fast.solve(q)
        assert np.abs(x - slow.solve(q)).max() < 1e-6 and np.all(np.abs(x) <= 0.5 + 1e-9)
        assert (fast.qp is None) == (scale < 1.0) == bool(np.all(np.abs(x) < 0.5))  # OSQP only when the box is active
    fast.set_P(2.0 * P)  # a new rho: the same as a box QP built with it
    assert np.abs(fast.solve(q) - BoxQP(2.0 * P, q, -0.5, 0.5, tight, False).solve(q)).max() < 1e-6


def test_reused_linearisation_is_exact_for_cv_and_second_order_for_a_reacting_predictor(states, analytic):
    _, src, s = analytic
    cv = make("two_lane", ["gradients=cv"])[1]
    st = states[3]
    Z = st.warm.Z
    d = np.zeros_like(Z)
    d[0::4], d[1::4] = 0.3, -0.2  # every step's ego x, y moved
    for source in (cv, src):
        reuse = Safety(source, st.obs.history, s.R, s.T_p)
        reuse.linearize(Z)
        errs = []
        for h in (1.0, 0.5):
            b, Jb = reuse.linearize(Z + h * d, reuse_radius=0.5)
            assert reuse.offset(Z + h * d) == pytest.approx(0.3 * h)  # reused, not taken afresh
            b0, _ = Safety(source, st.obs.history, s.R, s.T_p).linearize(Z + h * d)
            errs.append(np.abs(b - b0).max())
        if source is cv:  # the others ignore the ego: the ego's own part of b_i is exact, so all of it is
            assert max(errs) < 1e-9
        else:
            assert errs[0] > 1e-6 and errs[1] < 0.35 * errs[0]  # halving the offset quarters the error
    fresh = Safety(src, st.obs.history, s.R, s.T_p)
    fresh.linearize(Z)
    fresh.linearize(Z + d, reuse_radius=0.2)  # beyond the radius: linearised anew
    assert fresh.offset(Z + d) == 0.0


def test_dual_residual_is_the_delta_and_alpha_optimality_gap(states, analytic):
    _, src, s = analytic
    st = states[5]
    prob, start = mpc.build(s, st.obs, src, st.warm)
    old, _ = admm.admm_step(prob, start)
    new, _ = admm.admm_step(prob, old)
    A, B = prob.dyn.A, prob.dyn.B
    inside = np.all(np.abs(new.Delta) < 0.5) and np.all((new.alpha > -4.0) & (new.alpha < 3.0))
    assert inside  # with the boxes inactive, the sub-problems' gradients vanish at their own mu
    gap = np.concatenate([prob.Phi_1.P @ new.Delta + prob.Phi_1.q + A.T @ new.mu,
                          prob.Phi_2.P @ new.alpha + prob.Phi_2.q + B.T @ new.mu])
    assert np.linalg.norm(gap) > 1e-3
    assert admm.dual_residual(prob, old, new) == pytest.approx(np.linalg.norm(gap), rel=1e-5)


def test_set_rho_gives_the_problem_built_with_that_rho(states, analytic):
    _, src, s = analytic
    st = states[4]
    prob, start = mpc.build(s, st.obs, src, st.warm)
    prob.set_rho(37.0)
    other = make("two_lane", ["gradients=analytic", "mpc.rho=37.0"])[2]
    ref, _ = mpc.build(other, st.obs, src, st.warm)
    a, _ = admm.admm_step(prob, start)
    b, _ = admm.admm_step(ref, start)
    for f in ("Delta", "alpha", "Z", "mu"):
        assert np.abs(getattr(a, f) - getattr(b, f)).max() < 1e-6


def test_balanced_rho_converges_to_the_fixed_rho_plan(states, analytic):
    _, src, s = analytic
    bal = make("two_lane", ["gradients=analytic", "mpc.admm.balance_rho.enabled=true"])[2]
    for st in states[5:]:
        a, b = mpc.mpc_step(s, st.obs, src, st.warm), mpc.mpc_step(bal, st.obs, src, st.warm)
        if a.reason == b.reason == "converged":
            assert np.abs(a.u - b.u).max() <= 1e-2


def small_surrogate(tmp_path):
    """A random-weight JacobianNet beside a smooth student as the source, exported per window and as a rollout."""
    torch.manual_seed(1)
    net, source = JacobianNet(T_OBS, SLOTS, 16, 1, "").eval(), smooth_student()
    export(Fused(copy.deepcopy(net), copy.deepcopy(source)), tmp_path / "surrogate.onnx", T_OBS, SLOTS, "student")
    export_rollout(Rollout(copy.deepcopy(net), copy.deepcopy(source), 8), tmp_path / models.ROLLOUT, T_OBS, SLOTS, 8,
                   "student")
    return net, source


def test_rollout_export_matches_the_per_window_chain_rule(tmp_path, states):
    net, source = small_surrogate(tmp_path)
    st = states[3]
    history, ego = st.obs.history, ego_xy(st.warm.Z, 8)

    def phi_jac(w):
        with torch.no_grad():
            w = torch.as_tensor(w, dtype=torch.float32)
            return source(w).double().numpy(), net(w).double().numpy()

    values, grads = rollout_jacobian(phi_jac, history, ego)  # the per-window reference, composed in numpy
    with torch.no_grad():
        tv, tg = Rollout(net, source, 8)(torch.as_tensor(history[None]).float(), torch.as_tensor(ego[None]).float())
    assert np.abs(tv[0].numpy() - values).max() < 1e-4 and np.abs(tg[0].numpy() - grads).max() < 1e-5
    assert np.abs(grads[:, 1:]).max() > 1e-3  # the others' response to the ego plan is in it
    one = Surrogate("surrogate", None, models.load(tmp_path, rollout=True, T_p=8), rollout=True)
    per_window = Surrogate("surrogate", None, models.load(tmp_path), rollout=False)
    for a, b in zip(one.jacobian(history, ego), per_window.jacobian(history, ego)):
        assert np.abs(a - b).max() < 1e-5
    two = one.values(history, np.stack([ego, ego + 0.5]))  # any batch of plans in one call
    assert np.abs(two[0] - values).max() < 1e-4 and np.abs(two[1] - per_window.values(history, [ego + 0.5])[0]).max() < 1e-4
    assert np.abs(chain_rule(torch.as_tensor(np.stack([net(torch.zeros(1, T_OBS, SLOTS, 2)).detach().double().numpy()[0]] * 8))
                             ).numpy() - chain_rule(np.stack([net(torch.zeros(1, T_OBS, SLOTS, 2)).detach().double().numpy()[0]] * 8))
                  ).max() < 1e-12  # numpy and torch compose alike


def test_rollout_export_of_another_horizon_or_missing_is_refused(tmp_path):
    small_surrogate(tmp_path)
    with pytest.raises(UserError, match="paper.T_p=6"):
        models.load(tmp_path, rollout=True, T_p=6)
    (tmp_path / models.ROLLOUT).unlink()
    with pytest.raises(UserError, match="surrogate_rollout.onnx not found"):
        models.load(tmp_path, rollout=True, T_p=8)
    assert models.load(tmp_path).rollout_session is None  # the per-window path needs no rollout export


def test_crossing_bounds_are_a_solver_failure_not_a_silent_stale_solve():
    """OSQP keeps the previous bounds when an update has l > u; the QP wrapper must refuse instead."""
    qp = QP(np.eye(2), np.zeros(2), sparse.eye(2, format="csc"), -np.ones(2), np.ones(2), {})
    assert np.allclose(qp.solve(q=np.array([-5.0, 0.0])), [1.0, 0.0], atol=1e-3)
    with pytest.raises(SolverFailure, match="bounds cross"):
        qp.solve(l=np.array([2.0, -1.0]))
    assert np.allclose(qp.solve(l=np.array([0.5, -1.0]), q=np.zeros(2)), [0.5, 0.0], atol=1e-3)
