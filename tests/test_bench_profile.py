"""The step-time bench's profile: its OSQP solve count equals a count taken by wrapping the QP wrapper, its network call
count is zero for a source without a network, its DAQP count sees into the one-call ADMM solve, its parts add up to
the profiled step's time, and its MLflow metric names are ones MLflow accepts."""
import re
import time

import numpy as np

from bench import step_time
from bench.states import PlanningState, settings, solver_step
from data.world import backfill
from distill.predictors import ConstantVelocity
from planner import jit_zstep, mpc, qp
from planner.gradients import ExactLocal
from planner.setup import make


def test_profile_counts_osqp_solves_and_splits_the_step(monkeypatch):
    scenario, source = make("two_lane", ["gradients=analytic"])[:2]
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # nudged towards the platoon, so the safety constraints are active
    states = [PlanningState("two_lane", mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2)), None)]
    reference = lambda scenario: settings(scenario, ("mpc.admm.core=reference",))  # the numpy and OSQP core
    solver_step()(reference("two_lane"), states[0].obs, source, None)  # first-call costs (imports, set-ups) stay out
    counted = []
    solve = qp.QP.solve
    monkeypatch.setattr(qp.QP, "solve", lambda self, *a, **k: counted.append(1) or solve(self, *a, **k))
    t0 = time.perf_counter()
    ms, calls = step_time.profile(solver_step(), source, reference, states)
    wall_ms = 1e3 * (time.perf_counter() - t0)
    assert len(counted) > 0 and calls["OSQP solves"] == len(counted)
    assert "onnxruntime calls" not in calls
    assert 0.3 * wall_ms < sum(ms.values()) <= wall_ms
    assert any(k.startswith("planner/") for k in ms)
    ms, calls = step_time.profile(solver_step(), source, settings, states)  # the compiled core: numba and DAQP
    assert calls["DAQP solves"] > 0 and "OSQP solves" not in calls and ms["compiled kernels (numba)"] > 0
    keys = [step_time.profile_key("analytic", k) for k in [*ms, *calls, "<frozen importlib._bootstrap>"]]
    assert all(re.fullmatch(r"profile_analytic_[A-Za-z0-9_.-]+", k) for k in keys)  # names MLflow accepts


def test_profile_counts_the_daqp_solves_inside_a_one_call_admm_solve(monkeypatch):
    """cv's ADMM solve is one compiled call, which cProfile cannot see into: its DAQP count (the handles' counter) equals
    cProfile's count of the same solves driven from Python."""
    scenario, _, s = make("two_lane", ["gradients=cv"])
    source = ExactLocal("cv", ConstantVelocity())
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15
    states = [PlanningState("two_lane", mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2)), None)]
    solver_step()(s, states[0].obs, source, None)
    ms, calls = step_time.profile(solver_step(), source, lambda scenario: s, states)
    assert calls["one-call ADMM solves"] == 1 and ms["ADMM solve, one compiled call (numba + DAQP)"] > 0
    monkeypatch.setattr(jit_zstep, "compiled_params", lambda source: None)
    _, driven = step_time.profile(solver_step(), source, lambda scenario: s, states)
    assert "one-call ADMM solves" not in driven and calls["DAQP solves"] == driven["DAQP solves called from Python"] > 0


def test_profile_splits_a_known_step_per_state():
    def step(s, obs, src, warm):  # stands in for an MPC step: 10 ms in a C function (sleep), then a little own Python
        time.sleep(0.010)
        return sum(range(1000))

    ms, calls = step_time.profile(step, None, lambda scenario: None, [PlanningState("two_lane", None, None)] * 3)
    assert set(ms) == {"numpy / builtins", "tests/test_bench_profile.py"} and calls == {}
    assert 10.0 <= ms["numpy / builtins"] < 20.0  # per step, not summed over the 3 states; sleep can only overrun
    assert ms["tests/test_bench_profile.py"] < 2.0


def test_profile_counts_each_onnxruntime_call_once(tmp_path):
    import onnxruntime
    import torch

    torch.onnx.export(torch.nn.Linear(3, 2), (torch.zeros(1, 3),), str(tmp_path / "lin.onnx"), input_names=["x"],
                      dynamo=False)
    session = onnxruntime.InferenceSession(str(tmp_path / "lin.onnx"), providers=["CPUExecutionProvider"])

    def step(s, obs, src, warm):  # stands in for an MPC step that runs a network 7 times
        for _ in range(7):
            session.run(None, {"x": np.zeros((1, 3), np.float32)})

    states = [PlanningState("two_lane", None, None)] * 2
    _, calls = step_time.profile(step, None, lambda scenario: None, states)
    assert calls["onnxruntime calls"] == 7
