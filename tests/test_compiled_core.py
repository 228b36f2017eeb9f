"""The ADMM solve's kernels: the compiled rollouts, network Jacobians and b_i gradients against the reference maths
(core.rollout) and central differences, DAQP called from numba against daqp's own Model and an explicit slack QP, and
the one-call compiled solve against the same loop run from Python."""
import gc
import weakref

import daqp
import numpy as np
import pytest
import torch
from test_surrogate import smooth_student

from bench.states import collect, solver_step
from core.rollout import SLOTS, T_OBS, accelerations, b_i, b_i_jacobian, courtesy_jacobian, ego_xy, rollout_jacobian
from distill import student
from distill.models import StudentPredictor
from distill.predictors import ConstantVelocity
from planner import daqp_qp, jit_rollout, safety
from planner.gradients import ExactLocal, Surrogate
from planner.qp import QP, SolverFailure
from planner.setup import make
from surrogate import models
from surrogate.export import export
from surrogate.network import Fused, JacobianNet


@pytest.fixture(scope="module")
def states():
    """Planning states (observation, warm start) of a closed-loop two_lane run with the analytic predictor."""
    return collect(scenarios=("two_lane",), per_scenario=8, gradients="analytic")


def student_source():
    """The student source over a smooth random-weight student whose others react to the ego."""
    return ExactLocal("student", StudentPredictor(smooth_student()))


def surrogate_source(tmp_path):
    """A fused surrogate export as the planner loads one: a random-weight JacobianNet about constant velocity's Jacobian
    (as a trained one predicts about its training mean) beside the smooth student."""
    torch.manual_seed(1)
    net = JacobianNet(T_OBS, SLOTS, 16, 1, "").eval()
    with torch.no_grad():
        net.J_mean.copy_(torch.tensor(ConstantVelocity().phi_jac(np.zeros((1, T_OBS, SLOTS, 2)))[1].reshape(-1)))
        net.J_std.fill_(0.05)
    export(Fused(net, smooth_student()), tmp_path / "surrogate.onnx", T_OBS, SLOTS, "student")
    return Surrogate("surrogate", None, models.load(tmp_path, T_OBS, SLOTS - 1))


SOURCES = {"cv": lambda tmp: ExactLocal("cv", ConstantVelocity()), "analytic": lambda tmp: make("two_lane", ["gradients=analytic"])[1],
           "student": lambda tmp: student_source(), "surrogate": surrogate_source}


@pytest.mark.parametrize("name", ["cv", "student"])
def test_compiled_rollout_equals_the_reference_chain_rule(name, states):
    src = SOURCES[name](None)
    st = states[3]
    ego = ego_xy(st.warm.Z, 8).copy()
    got = jit_rollout.compiled_jacobian(src)(st.obs.history, ego)
    want = rollout_jacobian(src.predictor.phi_jac, st.obs.history, ego)
    assert np.abs(got[0] - want[0]).max() < 1e-10 and np.abs(got[1] - want[1]).max() < 1e-10


def test_compiled_student_jacobian_matches_central_differences(states):
    pred = StudentPredictor(smooth_student())
    Ws, bs, _ = jit_rollout.compiled_params(ExactLocal("student", pred))
    window = np.ascontiguousarray(states[3].obs.history)
    _, J = student.phi_jac(Ws, bs, pred.s, window)
    h, flat = 1e-5, window.reshape(-1)
    fd = np.stack([(student.phi_jac(Ws, bs, pred.s, (flat + h * e).reshape(window.shape))[0]
                    - student.phi_jac(Ws, bs, pred.s, (flat - h * e).reshape(window.shape))[0]).reshape(-1) / (2 * h)
                   for e in np.eye(flat.size)], axis=1)
    assert np.abs(J[2:]).max() > 1e-3 and np.abs(J - fd).max() < 1e-6


@pytest.mark.parametrize("stretch, p, R", [(1.0, 2.0, 3.95), (1.77, 2.0, 3.95), (2.05, 6.0, 2.2)])  # the paper's
def test_compiled_b_i_gradient_matches_the_reference_and_central_differences(states, stretch, p, R):  # circle, highway-env's ellipse, mpc=courteous's superellipse
    src, st = student_source(), states[3]
    ego0 = ego_xy(st.warm.Z, 8).copy()
    values0, grads = jit_rollout.compiled_jacobian(src)(st.obs.history, ego0)
    ego, Z = ego0 + 0.3, np.tile([0.0, 0.0, 0.1, 5.0], 8)
    Z.reshape(8, 4)[:, :2] = ego
    b, Jb = jit_rollout.rows_affine(Z, ego0, values0, grads, R, stretch, p, st.obs.history[-2:, :, 0].copy(), 0.2, 3.0,
                                     False)
    affine = lambda e: values0 + np.einsum("tmkse,se->tmk", grads, e - ego0)
    gap = affine(ego)[:, :1] - affine(ego)[:, 1:]  # (T_p, N, 2), by hand: R^2 (|dx / (stretch R)|^p + |dy / R|^p)^(2/p) - R^2
    by_hand = R**2 * (np.abs(gap[..., 0] / (stretch * R)) ** p + np.abs(gap[..., 1] / R) ** p) ** (2 / p) - R**2
    assert np.allclose(b, by_hand.T.reshape(-1))
    want = b_i_jacobian(affine(ego), grads, R, stretch, p)
    assert np.abs(b - want[0]).max() < 1e-9 and np.abs(Jb - want[1]).max() < 1e-9
    h = 1e-6
    fd = np.stack([(b_i(affine(ego_xy(Z + h * e, 8)), R, stretch, p) - b_i(affine(ego_xy(Z - h * e, 8)), R, stretch, p)).reshape(-1)
                   / (2 * h)
                   for e in np.eye(Z.size)], axis=1)
    assert np.abs(Jb - fd).max() < 1e-5 * max(1.0, np.abs(Jb).max())


def test_courtesy_rows_are_the_others_second_differences_and_their_gradient_matches_differences(states):
    """c_i = a_i + b_c from the predicted x of the other cars (the last two observed steps first), its compiled and
    reference derivatives against central differences of the student's affine rollout."""
    src, st, dt, b_c = student_source(), states[3], 0.2, 3.0
    hist = np.ascontiguousarray(st.obs.history)
    ego0 = ego_xy(st.warm.Z, 8).copy()
    values0, grads = jit_rollout.compiled_jacobian(src)(hist, ego0)
    x = np.concatenate([hist[-2:, 2, 0], values0[:, 2, 0]])  # car 2 (slot 2), by hand
    a = [(x[t + 2] - 2 * x[t + 1] + x[t]) / dt**2 for t in range(8)]
    assert np.allclose(accelerations(values0, hist, dt)[1], a)
    ego, Z = ego0 + 0.3, np.tile([0.0, 0.0, 0.1, 5.0], 8)
    Z.reshape(8, 4)[:, :2] = ego
    affine = lambda e: values0 + np.einsum("tmkse,se->tmk", grads, e - ego0)
    stacked, J = jit_rollout.rows_affine(Z, ego0, values0, grads, 3.95, 1.0, 2.0, hist[-2:, :, 0].copy(), dt, b_c, True)
    c, Jc = stacked[32:], J[32:]  # after the N*T_p = 32 b_i rows, which stay b_i_jacobian's
    assert np.abs(stacked[:32] - b_i_jacobian(affine(ego), grads, 3.95)[0]).max() < 1e-9
    want = courtesy_jacobian(affine(ego), grads, hist, dt, b_c)
    assert np.abs(c - want[0]).max() < 1e-9 and np.abs(Jc - want[1]).max() < 1e-9
    h = 1e-6
    rows = lambda Z_: accelerations(affine(ego_xy(Z_, 8)), hist, dt).reshape(-1) + b_c
    fd = np.stack([(rows(Z + h * e) - rows(Z - h * e)) / (2 * h) for e in np.eye(Z.size)], axis=1)
    assert np.abs(Jc).max() > 1e-3 and np.abs(Jc - fd).max() < 1e-4 * max(1.0, np.abs(Jc).max())


def test_soft_qp_prices_violations_like_the_explicit_slack_qp():
    """DAQP's soft rows with the L1 price give the Z-step's elastic QP (slack variables s >= 0 priced linearly), solved
    here by OSQP at tight tolerances, also where the rows cannot all hold inside the box."""
    rng = np.random.default_rng(0)
    n, m, price = 6, 4, 50.0
    L = rng.normal(size=(n, n))
    H, f, A = L @ L.T + n * np.eye(n), rng.normal(size=n), rng.normal(size=(m, n))
    lo, hi = -np.ones(n), np.ones(n)
    c_lo = np.array([20.0, -1.0, 0.5, 30.0])  # rows 0 and 3 out of reach in the box: violated at a price
    x = daqp_qp.optimal(*daqp_qp.solve(daqp_qp.handle(n, m, True, price), True, H, f, lo, hi, A, c_lo))
    P = np.block([[H, np.zeros((n, m))], [np.zeros((m, n)), np.zeros((m, m))]])
    G = np.block([[np.eye(n), np.zeros((n, m))], [A, np.eye(m)], [np.zeros((m, n)), np.eye(m)]])
    tight = {"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 200000, "polishing": True}
    want = QP(P, np.concatenate([f, np.full(m, price)]), G, np.concatenate([lo, c_lo, np.zeros(m)]),
              np.concatenate([hi, np.full(2 * m, np.inf)]), tight).solve()
    assert np.max(c_lo - A @ x) > 1.0  # the price is paid, not the rows enforced
    assert np.abs(x - want[:n]).max() < 1e-5


def test_daqp_called_from_numba_solves_as_daqp_model_warm_started():
    """planner.daqp_qp's C calls (its own struct layouts) against daqp's Python Model on one sequence of soft-row QPs,
    the second and later solves warm-started from the last working set in both."""
    rng = np.random.default_rng(0)
    n, m, price = 16, 12, 1e3
    L = rng.normal(size=(n, n))
    H = L @ L.T + n * np.eye(n)
    mine, model = daqp_qp.handle(n, m, True, price), daqp.Model()
    sense = np.concatenate([np.zeros(n), np.full(m, daqp_qp.SOFT)]).astype(np.int32)
    for k in range(20):
        f, A, c_lo = 10 * rng.normal(size=n), rng.normal(size=(m, n)), 3 * rng.normal(size=m)
        bu, bl = np.concatenate([np.ones(n), np.full(m, daqp_qp.INF)]), np.concatenate([-np.ones(n), c_lo])
        if k == 0:
            model.setup(H, f, A, bu, bl, sense)
            weights = np.full(n + m, daqp_qp.SOFT_RHO)
            model.soft_weights(rho_l=weights, rho_u=weights, w_l=np.full(n + m, price), w_u=np.full(n + m, price))
        else:
            model.update(f=f, A=A, bupper=bu, blower=bl)
        want, _, flag, _ = model.solve()
        x, mine_flag = daqp_qp.solve(mine, k == 0, H, f, -np.ones(n), np.ones(n), A, c_lo)
        assert flag >= 1 and mine_flag >= 1 and np.abs(x - want).max() < 1e-9


def test_a_failed_daqp_solve_is_a_solver_failure():
    """An infeasible hard row (c_lo above what the box allows) is DAQP's exit flag, raised as the planner's SolverFailure."""
    qp = daqp_qp.handle(2, 1)
    with pytest.raises(SolverFailure, match="DAQP exit flag"):
        daqp_qp.optimal(*daqp_qp.solve(qp, True, np.eye(2), np.zeros(2), -np.ones(2), np.ones(2), np.ones((1, 2)),
                                       np.array([5.0])))


@pytest.mark.parametrize("name", ["cv", "student"])
def test_one_call_admm_solve_equals_the_same_kernels_driven_from_python(name, states, tmp_path, monkeypatch):
    """The compiled predictors' one-call ADMM solve (planner.admm.admm_loop compiled) and the same loop run from Python
    over the same kernels (taken when the safety has no compiled predictor) give the same iterates to rounding, step
    for step."""
    src = SOURCES[name](tmp_path)
    s = make("two_lane", ["gradients=analytic"])[2]
    one_call = [solver_step()(s, st.obs, src, st.warm) for st in states]
    monkeypatch.setattr(safety, "compiled_params", lambda source: None)  # the same compiled rollouts, called from Python
    driven = [solver_step()(s, st.obs, src, st.warm) for st in states]
    for a, b in zip(one_call, driven):
        assert (a.reason, a.iters, a.fallback) == (b.reason, b.iters, b.fallback)
        if a.plan is not None:
            assert np.abs(a.plan.Z - b.plan.Z).max() < 1e-7 and np.abs(a.u - b.u).max() < 1e-9


def test_a_dropped_daqp_workspace_is_released():
    """A handle's workspace is freed with it: nothing (its finaliser included) keeps it alive, so a process that sets
    up handles does not grow without bound."""

    h = daqp_qp.handle(4, 2, True, 1.0)
    work = weakref.ref(h.work)
    del h
    gc.collect()
    assert work() is None
