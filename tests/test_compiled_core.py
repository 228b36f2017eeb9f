"""The compiled core (mpc.admm.core=compiled: numba kernels, DAQP) gives the reference core's plans (numpy, OSQP solved
tight) on saved planning states for every source it runs, and its compiled rollouts, network Jacobians and b_i
gradients match the reference maths and central differences."""
import gc
import weakref

import daqp
import numpy as np
import pytest
import torch
from test_surrogate import smooth_student

from bench.states import collect, solver_step
from core.rollout import SLOTS, T_OBS, accelerations, b_i, b_i_jacobian, courtesy_jacobian, ego_xy, rollout_jacobian
from distill.models import StudentPredictor
from distill.predictors import ConstantVelocity
from planner import daqp_qp, jit_rollout, jit_zstep, mpc
from planner.daqp_qp import SoftQP
from planner.gradients import ExactLocal, Surrogate
from planner.qp import QP, SolverFailure
from planner.setup import drive, make, planner_config, setup
from surrogate import models
from surrogate.export import export
from surrogate.network import Fused, JacobianNet

TIGHT = ("mpc.admm.osqp.eps_abs=1e-7", "mpc.admm.osqp.eps_rel=1e-7", "mpc.admm.osqp.max_iter=20000")  # the reference's QPs near exact
U_TOL, Z_TOL = 5e-3, 1e-2  # rad or m/s^2, and m: a few times ADMM's tol_step (1e-3), where both converged


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


@pytest.mark.parametrize("name", list(SOURCES))
def test_compiled_step_gives_the_reference_plan(name, states, tmp_path):
    src = SOURCES[name](tmp_path)
    compiled = make("two_lane", ["gradients=analytic", "mpc.admm.core=compiled"])[2]
    reference = make("two_lane", ["gradients=analytic", "mpc.admm.core=reference", *TIGHT])[2]
    both = 0
    for st in states:
        a, b = solver_step()(compiled, st.obs, src, st.warm), solver_step()(reference, st.obs, src, st.warm)
        if "converged" in (a.reason, b.reason):  # unconverged (max_iters) runs end anywhere: only converged ones compare
            assert a.reason == b.reason == "converged"
            both += 1
            assert np.abs(a.u - b.u).max() <= U_TOL and np.abs(a.plan.Z - b.plan.Z).max() <= Z_TOL
            assert abs(a.J - b.J) <= 1e-3 * max(abs(b.J), 1.0)
    assert both >= 3


@pytest.mark.parametrize("name", ["cv", "analytic"])
def test_the_cores_take_the_same_iteration_before_they_converge(name, states, tmp_path):
    """The first four ADMM iterations, long before convergence, each from the same iterate (the reference's) in both
    cores (cv: the one-call solve; analytic: its kernels driven from Python): the same trust radius always, and the same
    iterate wherever the linearised rows can be met (no slack paid), so the cores share the trust-region test and its
    constants, not only the fixed points they converge to. (Where slack is paid the two soft-row QPs part: DAQP's soft
    rows and OSQP's elastic slack price a violation differently.)"""
    src = SOURCES[name](tmp_path)
    cores = (make("two_lane", ["gradients=analytic", "mpc.admm.core=compiled"])[2],
             make("two_lane", ["gradients=analytic", "mpc.admm.core=reference", *TIGHT])[2])
    zstep = solver_step().keywords["zstep"]
    radii, compared = set(), 0
    for st in states:
        built = [mpc.build(s, st.obs, src, st.warm, zstep) for s in cores]
        it = built[1][2]
        for _ in range(4):
            (a, out_a), (b, out_b) = (s.core.solve(prob, solvers, it, 1, 1e-12, 1e-12)
                                      for s, (prob, solvers, _) in zip(cores, built))
            assert out_a.reason == out_b.reason == "max_iters" and a.zstate.radius == b.zstate.radius
            radii.add(b.zstate.radius)
            if max(out_a.zinfo["slack"], out_b.zinfo["slack"]) < 1e-6:
                compared += 1
                assert max(np.abs(x - y).max() for x, y in zip(a[:3], b[:3])) < 1e-4  # Delta, alpha, Z
                assert np.abs(a.mu - b.mu).max() < 1e-3 * built[1][0].rho  # mu moves by rho F: rho times a few Z errors
            it = b
    assert compared >= 24 and len(radii) > 1  # most iterations compared; the radius grown or cut on the way


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
    _, J = jit_rollout.student_phi_jac(Ws, bs, pred.s, window)
    h, flat = 1e-5, window.reshape(-1)
    fd = np.stack([(jit_rollout.student_phi_jac(Ws, bs, pred.s, (flat + h * e).reshape(window.shape))[0]
                    - jit_rollout.student_phi_jac(Ws, bs, pred.s, (flat - h * e).reshape(window.shape))[0]).reshape(-1) / (2 * h)
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
    x = SoftQP(H, price, True, m).solve(f, lo, hi, A, c_lo)
    P = np.block([[H, np.zeros((n, m))], [np.zeros((m, n)), np.zeros((m, m))]])
    G = np.block([[np.eye(n), np.zeros((n, m))], [A, np.eye(m)], [np.zeros((m, n)), np.eye(m)]])
    tight = {"eps_abs": 1e-10, "eps_rel": 1e-10, "max_iter": 200000, "polishing": True}
    want = QP(P, np.concatenate([f, np.full(m, price)]), G, np.concatenate([lo, c_lo, np.zeros(m)]),
              np.concatenate([hi, np.full(2 * m, np.inf)]), tight).solve()
    assert np.max(c_lo - A @ x) > 1.0  # the price is paid, not the rows enforced
    assert np.abs(x - want[:n]).max() < 1e-5


def test_compiled_closed_loop_drives_the_reference_episode_with_cv():
    """Table II's two_lane merge with constant velocity, whose steps converge: the same episode, step for step. (With
    steps that stop at max_iters, as the trained predictors' often do, episodes part as they do when only OSQP's
    tolerance changes: there the batch statistics compare.)"""
    episodes = []
    for core in ("compiled", "reference"):
        cfg = planner_config("two_lane", ["gradients=cv", "method=admm", f"mpc.admm.core={core}", *TIGHT])
        scenario, src, s = setup(cfg)
        episodes.append(drive(cfg, scenario, src, s, "admm"))
    a, b = episodes
    assert len(a.controls) == len(b.controls) and not a.collided and not b.collided
    assert np.abs(a.controls - b.controls).max() <= U_TOL
    assert [bool(r["fallback"]) for r in a.rows] == [bool(r["fallback"]) for r in b.rows]


def test_daqp_called_from_numba_solves_as_daqp_model_warm_started():
    """planner.daqp_qp's C calls (its own struct layouts) against daqp's Python Model on one sequence of soft-row QPs,
    the second and later solves warm-started from the last working set in both."""
    rng = np.random.default_rng(0)
    n, m, price = 16, 12, 1e3
    L = rng.normal(size=(n, n))
    H = L @ L.T + n * np.eye(n)
    mine, model = SoftQP(H, price, True, m), daqp.Model()
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
        assert flag >= 1 and np.abs(mine.solve(f, -np.ones(n), np.ones(n), A, c_lo) - want).max() < 1e-9


def test_a_failed_daqp_solve_is_a_solver_failure():
    """An infeasible hard row (c_lo above what the box allows) is DAQP's exit flag, raised as the planner's SolverFailure."""
    qp = SoftQP(np.eye(2), 1.0, False, 1)
    with pytest.raises(SolverFailure, match="DAQP exit flag"):
        qp.solve(np.zeros(2), -np.ones(2), np.ones(2), np.ones((1, 2)), np.array([5.0]))


@pytest.mark.parametrize("name", ["cv", "student"])
def test_one_call_admm_solve_equals_the_same_kernels_driven_from_python(name, states, tmp_path, monkeypatch):
    """The compiled predictors' one-call ADMM solve (jit_admm.admm_loop) and the Python-driven loop over the same kernels
    (taken when the safety has no compiled predictor) give the same iterates to rounding, step for step."""
    src = SOURCES[name](tmp_path)
    s = make("two_lane", ["gradients=analytic", "mpc.admm.core=compiled"])[2]
    one_call = [solver_step()(s, st.obs, src, st.warm) for st in states]
    monkeypatch.setattr(jit_zstep, "compiled_params", lambda source: None)  # the same compiled rollouts, called from Python
    driven = [solver_step()(s, st.obs, src, st.warm) for st in states]
    for a, b in zip(one_call, driven):
        assert (a.reason, a.iters, a.fallback) == (b.reason, b.iters, b.fallback)
        if a.plan is not None:
            assert np.abs(a.plan.Z - b.plan.Z).max() < 1e-7 and np.abs(a.u - b.u).max() < 1e-9


def test_a_dropped_daqp_workspace_is_released():
    """A handle's workspace is freed with it: nothing (its finaliser included) keeps it alive, so a long batch that
    builds Z-steps from Python does not grow without bound."""

    h = daqp_qp.handle(4, 2, True, 1.0)
    work = weakref.ref(h.work)
    del h
    gc.collect()
    assert work() is None
