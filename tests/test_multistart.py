"""The multi-start step (mpc=courteous) solves all its starts in one compiled call for the sources the compiled core runs
itself (cv, the student): every start gets the plan, check and reason it gets solved alone, so the step chooses the same
plan; the other sources, and a joint call that fails, take the one-by-one path."""
from dataclasses import replace

import numpy as np
import pytest
from test_surrogate import smooth_student

from core import jit_linalg
from distill.models import StudentPredictor
from distill.predictors import ConstantVelocity
from planner import admm, mpc, step
from planner.gradients import ExactLocal
from planner.setup import make

SOURCES = {"cv": lambda: ExactLocal("cv", ConstantVelocity()),
           "student": lambda: ExactLocal("student", StudentPredictor(smooth_student()))}


def _observation(y, v, cars):
    """two_lane: the ego at (0, y) at v m/s and the four others (core.rollout.SLOTS) at `cars` [(x m, y m, v m/s,
    slowing m/s^2)], eight steps of history of 0.2 s."""
    t = np.arange(7, -1, -1) * 0.2  # s before now
    ego = np.stack([-v * t, np.full(8, y)], 1)
    others = [np.stack([x - u * t - 0.5 * a * t**2, np.full(8, cy)], 1) for x, cy, u, a in cars]
    return mpc.Observation(np.array([0.0, y, 0.0, v]), np.zeros(2), np.stack([ego, *others], 1))


@pytest.fixture(scope="module")
def states():
    """mpc=courteous on two_lane and (observation, warm start) pairs: leaning beside a car, in lane before a gap, and in
    lane beside a car seen slowing (KeepAhead's lean); each cold and warm-started from its cold step's plan."""
    _, _, s = make("two_lane", ["gradients=cv", "mpc=courteous"])
    observations = [_observation(1.9, 5.0, [(0.5, 4.0, 5.0, 0.0), (60.0, 4.0, 5.0, 0.0), (80.0, 4.0, 5.0, 0.0),
                                            (100.0, 4.0, 5.0, 0.0)]),
                    _observation(0.0, 6.0, [(-12.0, 4.0, 5.0, 0.0), (14.0, 4.0, 5.0, 0.0), (40.0, 4.0, 5.0, 0.0),
                                            (-40.0, 4.0, 5.0, 0.0)]),
                    _observation(1.9, 4.0, [(-4.0, 4.0, 4.0, 1.5), (9.0, 4.0, 5.0, 0.0), (30.0, 4.0, 5.0, 0.0),
                                            (-30.0, 4.0, 5.0, 0.0)])]
    cv, zstep = SOURCES["cv"](), _zstep()
    warm = [step.mpc_step(s, obs, cv, None, zstep).plan for obs in observations]
    return s, zstep, [(obs, None) for obs in observations] + list(zip(observations, warm))


def _zstep():
    """The bound sqp Z-step of the planner's config."""
    from hydra.utils import instantiate

    from planner.setup import planner_config

    return instantiate(planner_config("two_lane", ["gradients=cv"]).solver.step).keywords["zstep"]


def _counted(monkeypatch):
    """A list that grows by the number of solves at each call of the compiled multi-start solve."""
    calls, solves = [], admm.compiled_solves
    monkeypatch.setattr(admm, "compiled_solves", lambda batch: calls.append(len(batch)) or solves(batch))
    return calls


def _alone(s, obs, source, starts, zstep):
    """Each start solved by itself."""
    return [step.solve_all(s, obs, source, [st], zstep)[0] for st in starts]


def _same(a, b):
    """Whether two solves' (StepResult or None, why) agree exactly: plan, control, cost, checks, reason."""
    (ra, why_a), (rb, why_b) = a, b
    if ra is None or rb is None:
        return ra is rb and why_a == why_b
    return (all(np.array_equal(x, y) for x, y in zip(ra.plan[:4], rb.plan[:4])) and np.array_equal(ra.u, rb.u)
            and (ra.J, ra.iters, ra.reason, ra.b_min, ra.braking, ra.c_min) == (rb.J, rb.iters, rb.reason, rb.b_min, rb.braking, rb.c_min))


@pytest.mark.parametrize("name", list(SOURCES))
def test_all_starts_in_one_call_give_each_start_its_own_plan_and_the_same_choice(name, states, monkeypatch):
    s, zstep, pairs = states
    source, calls = SOURCES[name](), _counted(monkeypatch)
    for obs, warm in pairs:
        starts = s.strategy.candidates(s, obs, warm, source)
        del calls[:]
        joint = step.solve_all(s, obs, source, starts, zstep)
        assert calls == [len(starts)] == [3]  # one compiled call for the step's three starts
        alone = _alone(s, obs, source, starts, zstep)
        assert len(calls) == 1 + len(starts)
        assert all(_same(a, b) for a, b in zip(joint, alone))
        chosen = step.mpc_step(s, obs, source, warm, zstep)
        _, expected = s.strategy.choose(s, obs, [(st, r) for st, (r, _) in zip(starts, alone) if r is not None])
        assert chosen.fallback == "" and np.array_equal(chosen.plan.Delta, expected.plan.Delta)
        assert np.array_equal(chosen.plan.alpha, expected.plan.alpha)


def test_a_source_the_core_does_not_run_and_a_failed_joint_call_take_the_one_by_one_path(states, monkeypatch):
    s, zstep, pairs = states
    obs, warm = pairs[1]
    analytic, calls = make("two_lane", ["gradients=analytic"])[1], _counted(monkeypatch)
    starts = s.strategy.candidates(s, obs, warm, analytic)
    assert [r is not None for r, _ in step.solve_all(s, obs, analytic, starts, zstep)] == [True] * 3 and calls == []
    cv = SOURCES["cv"]()
    starts = s.strategy.candidates(s, obs, warm, cv)
    alone = _alone(s, obs, cv, starts, zstep)
    del calls[:]
    counted = admm.compiled_solves
    fail_once = lambda batch: (calls.append("failed"), monkeypatch.setattr(admm, "compiled_solves", counted))[0] and 1 / 0
    monkeypatch.setattr(admm, "compiled_solves", fail_once)
    assert all(_same(a, b) for a, b in zip(step.solve_all(s, obs, cv, starts, zstep), alone))
    assert calls == ["failed", 1, 1, 1]  # then each start in a call of its own


def test_a_kernel_called_through_its_entry_point_gives_its_result_and_no_two_numba_types_share_an_entry():
    from numba import typeof
    from numba.typed import List

    M, x = np.arange(6.0).reshape(2, 3), np.array([1.0, -2.0, 0.5])
    assert np.array_equal(admm.typed_call(jit_linalg.matvec, M, x), M @ x)  # typed by numba, the entry kept
    assert np.array_equal(admm.typed_call(jit_linalg.matvec, 2 * M, x), 2 * M @ x)  # through the kept entry
    readonly = x.copy()
    readonly.flags.writeable = False
    typed_list = List([x])
    samples = [x, np.asfortranarray(M), M, M[:, ::2], readonly, x.astype(np.float32), np.zeros(3, bool), 1, 1.0, True,
               np.float64(1.0), (x, 1), (1, x), admm.Stop(1, 1.0, 1.0), (1, 1.0, 1.0), typed_list, List([M])]
    for a in samples:
        for b in samples:
            assert admm.structure(a) != admm.structure(b) or typeof(a) == typeof(b), (a, b)  # one entry, one type


def _leaves(x):
    """The numbers of a set-up (build's Problem, Solvers, start): arrays and scalars, in order, through tuples (the
    box QPs among them) and the Z-step's data."""
    if isinstance(x, tuple):
        return [leaf for item in x for leaf in _leaves(item)]
    if hasattr(x, "data"):  # the compiled Z-step
        return _leaves(x.data)
    return [x]


def test_a_start_that_only_aims_elsewhere_shares_a_set_up_and_gets_the_numbers_of_its_own(states):
    s, zstep, pairs = states
    cv = SOURCES["cv"]()
    for obs, warm in pairs:
        first, *others = s.strategy.candidates(s, obs, warm, cv)
        base = mpc.build(first.aim, obs, cv, None, zstep, first.plan)
        for st in others:
            assert (st.aim.y_ref, st.aim.v_ref) != (s.y_ref, s.v_ref) and mpc.alike(first.aim, st.aim)
            shared = mpc.build(st.aim, obs, cv, None, zstep, st.plan, base)
            alone = mpc.build(st.aim, obs, cv, None, zstep, st.plan)
            assert shared[0].dyn is base[0].dyn and shared[1].delta_qp is base[1].delta_qp  # set up once
            a, b = _leaves(shared), _leaves(alone)
            assert len(a) == len(b) > 20 and all(np.array_equal(x, y) for x, y in zip(a, b))
            assert not np.array_equal(shared[0].Phi_3.q, base[0].Phi_3.q)  # its own references
    along = replace(s, linearize="along_plan")  # the dynamics then depend on each start's plan
    assert not mpc.alike(along, replace(along, y_ref=4.0)) and mpc.alike(s, replace(s, y_ref=4.0, v_ref=1.0))
    assert not mpc.alike(s, replace(s, b_courtesy=2.0)) and not mpc.alike(s, replace(s, T_p=s.T_p + 1))


def test_lane_plans_rolled_out_together_are_each_plan_alone_and_its_rollout(states):
    from data import bicycle
    from data.world import steer_to

    s = states[0]
    for z0 in ([0.0, 1.9, 0.05, 5.0], [3.0, 2.2, -0.1, 0.3], [0.0, 0.1, 0.0, 12.0]):  # leaning, straddling, in lane
        accels = [-1.0, -2.0, 0.5, 9.0, -50.0]  # beyond a_box both ways; hard braking meets the stop
        Delta, alpha, Z = mpc.lane_plans(s, np.array(z0), accels)
        for k, a in enumerate(accels):
            z, lane_y = np.array(z0), s.road.centre(s.road.lane_of(z0[1]))
            if abs(z0[1] - lane_y) > (s.road.lane_width - s.road.car_width) / 2:
                lane_y = s.road.centre(s.road.lane_of(z0[1] - np.sign(s.y_ref - z0[1]) * s.road.lane_width / 2))
            for t in range(s.T_p):  # lane_plan as it was, one plan and one step at a time
                d = float(np.clip(steer_to(z, lane_y, s.params), *s.delta_box))
                acc = max(float(np.clip(a, *s.a_box)), -z[3] / s.params.dt)
                assert np.isclose(Delta[k, t], d, rtol=1e-13, atol=1e-13) and np.isclose(alpha[k, t], acc, rtol=1e-13)
                z = bicycle.step(z, [Delta[k, t], alpha[k, t]], s.params)
            assert np.array_equal(Z[k], mpc.simulate(z0, Delta[k], alpha[k], s.params))
        assert np.any(alpha == -np.array(z0)[3] / s.params.dt) or z0[3] > 1.0


def test_plans_simulated_together_are_each_simulated_alone_step_by_step(states):
    from data import bicycle

    s, rng = states[0], np.random.default_rng(3)
    z0 = np.array([1.0, 1.9, 0.05, 5.0])
    Delta, alpha = rng.uniform(-0.5, 0.5, (4, s.T_p)), rng.uniform(-6.0, 3.0, (4, s.T_p))
    Z = mpc.simulate(z0, Delta, alpha, s.params)
    assert Z.shape == (4, 4 * s.T_p)
    for k in range(4):
        z, alone = z0, []
        for d, a in zip(Delta[k], alpha[k]):  # simulate as it was: one plan, one step at a time
            z = bicycle.step(z, [d, a], s.params)
            alone.append(z)
        # compiled (planner.jit_bicycle): the world's bicycle to rounding, and the same numbers together as alone
        assert np.allclose(Z[k], np.concatenate(alone), rtol=1e-13, atol=1e-13)
        assert np.array_equal(Z[k], mpc.simulate(z0, Delta[k], alpha[k], s.params))
