"""The MPC step's fast paths give the slow paths' plans: closed-form box QPs, reused linearisations, one SQP step per
ADMM iteration, the fused surrogate export (speed: `make bench`)."""
import copy

import numpy as np
import pytest
import torch
from scipy import sparse
from test_surrogate import smooth_student

from bench.states import collect, solver_step
from core.rollout import SLOTS, T_OBS, ego_xy, rollout_jacobian
from planner import admm, daqp_qp, mpc
from planner.gradients import Surrogate
from planner.qp import QP, SolverFailure
from planner.safety import Safety
from planner.setup import make
from surrogate import models
from surrogate.export import export
from surrogate.network import Fused, JacobianNet

SLOW = ("zstep.settings.reuse_radius=0", "zstep.settings.max_iters=2")  # two SQP steps, each from a fresh linearisation


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
        a, b = solver_step()(fast, st.obs, src, st.warm), solver_step(SLOW)(slow, st.obs, src, st.warm)
        assert bool(a.fallback) == bool(b.fallback)
        if a.reason == b.reason == "converged":  # the same fixed point to a few times ADMM's tol_step (1e-3)
            both += 1
            assert np.abs(a.u - b.u).max() <= 5e-3 and np.abs(a.plan.Z - b.plan.Z).max() <= 1e-2
    assert both >= 3


def test_box_qp_closed_form_equals_osqp_inside_and_on_the_box(states, analytic):
    _, src, s = analytic
    prob, solvers, _ = mpc.build(s, states[2].obs, src, states[2].warm, solver_step().keywords["zstep"])
    P = prob.Phi_1.P + s.admm.rho * prob.dyn.A.T @ prob.dyn.A
    box = solvers.delta_qp._replace(lo=np.full(len(P), -0.5), hi=np.full(len(P), 0.5))
    assert np.array_equal(box.P, P)  # the Delta-update's QP: P_1 + rho A'A
    tight = {"eps_abs": 1e-9, "eps_rel": 1e-9, "max_iter": 100000, "polishing": True}
    rng = np.random.default_rng(0)
    for scale in (0.01, 300.0):  # unconstrained minimiser inside the box, then mostly outside it
        q = scale * rng.normal(size=len(P))
        update = (*admm.box_minimiser(box.P_inv, q, box.lo, box.hi), q)
        x, flag, called = admm.box_update(daqp_qp.handle(len(P)), True, box, update)
        osqp = QP(P, q, sparse.eye(len(P), format="csc"), box.lo, box.hi, tight).solve()
        assert flag == 1 and np.abs(x - osqp).max() < 1e-6 and np.all(np.abs(x) <= 0.5 + 1e-9)
        assert (not called) == (scale < 1.0) == bool(np.all(np.abs(x) < 0.5))  # DAQP only when the box is active


def test_reused_linearisation_is_exact_for_cv_and_second_order_for_a_reacting_predictor(states, analytic):
    _, src, s = analytic
    cv = make("two_lane", ["gradients=cv"])[1]
    st = states[3]
    Z = st.warm.Z
    d = np.zeros_like(Z)
    d[0::4], d[1::4] = 0.3, -0.2  # every step's ego x, y moved
    for source in (cv, src):
        safety = Safety(source, st.obs.history, s.R, s.T_p)
        lin = safety.linearize(Z)[2]
        errs = []
        for h in (1.0, 0.5):
            b, Jb, kept = safety.linearize(Z + h * d, lin, reuse_radius=0.5)
            assert kept is lin and safety.offset(Z + h * d, lin) == pytest.approx(0.3 * h)  # reused, not taken afresh
            b0, _, _ = safety.linearize(Z + h * d)
            errs.append(np.abs(b - b0).max())
        if source is cv:  # the others ignore the ego: the ego's own part of b_i is exact, so all of it is
            assert max(errs) < 1e-9
        else:
            assert errs[0] > 1e-6 and errs[1] < 0.35 * errs[0]  # halving the offset quarters the error
    fresh = Safety(src, st.obs.history, s.R, s.T_p)
    new = fresh.linearize(Z + d, fresh.linearize(Z)[2], reuse_radius=0.2)[2]  # beyond the radius: linearised anew
    assert fresh.offset(Z + d, new) == 0.0


def test_fused_surrogate_source_matches_the_torch_chain_rule(tmp_path, states):
    """A random-weight JacobianNet beside a smooth student as the source, exported fused: the planner's source gives
    their torch values and Jacobians composed per window."""
    torch.manual_seed(1)
    net, source = JacobianNet(T_OBS, SLOTS, 16, 1, "").eval(), smooth_student()
    export(Fused(copy.deepcopy(net), copy.deepcopy(source)), tmp_path / "surrogate.onnx", T_OBS, SLOTS, "student")
    st = states[3]
    history, ego = st.obs.history, ego_xy(st.warm.Z, 8)

    def phi_jac(w):
        with torch.no_grad():
            w = torch.as_tensor(w, dtype=torch.float32)
            return source(w).double().numpy(), net(w).double().numpy()

    values, grads = rollout_jacobian(phi_jac, history, ego)  # the reference: torch's values and J, composed in numpy
    assert np.abs(grads[:, 1:]).max() > 1e-3  # the others' response to the ego plan is in it
    fused = Surrogate("surrogate", None, models.load(tmp_path, T_OBS, SLOTS - 1))  # no predictor: the export carries the source's phi
    assert fused.joint  # values come with J in one onnxruntime call, so Safety.trial linearises trial plans
    got = fused.jacobian(history, ego)  # float32 onnxruntime against float32 torch: J at windows ~1e-5 m apart
    assert np.abs(got[0] - values).max() < 1e-4 and np.abs(got[1] - grads).max() < 1e-4
    two = fused.values(history, np.stack([ego, ego + 0.5]))  # a batch of plans; float32 at tens of metres
    shifted = rollout_jacobian(phi_jac, history, ego + 0.5)[0]
    assert np.abs(two[0] - values).max() < 1e-3 and np.abs(two[1] - shifted).max() < 1e-3
    assert np.abs(shifted - values)[:, 1:].max() > 1e-2  # the others respond to the shift: the batch is not one plan


def test_crossing_bounds_are_a_solver_failure_not_a_silent_stale_solve():
    """OSQP keeps the previous bounds when an update has l > u; the QP wrapper must refuse instead."""
    qp = QP(np.eye(2), np.zeros(2), sparse.eye(2, format="csc"), -np.ones(2), np.ones(2), {})
    assert np.allclose(qp.solve(q=np.array([-5.0, 0.0])), [1.0, 0.0], atol=1e-3)
    with pytest.raises(SolverFailure, match="bounds cross"):
        qp.solve(l=np.array([2.0, -1.0]))
    assert np.allclose(qp.solve(l=np.array([0.5, -1.0]), q=np.zeros(2)), [0.5, 0.0], atol=1e-3)
