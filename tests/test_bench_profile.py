"""The step-time bench's profile: its DAQP solve count equals cProfile's count of the same solves called from Python and
sees into the one-call ADMM solve, its network call count is zero for a source without a network, its parts add up to
the profiled step's time, and its MLflow metric names are ones MLflow accepts."""
import re
import time

import numpy as np

from bench import step_time
from bench.states import PlanningState, settings, solver_step
from data.world import backfill
from distill.predictors import ConstantVelocity
from planner import mpc, safety
from planner.gradients import ExactLocal
from planner.setup import make


def test_profile_counts_daqp_solves_and_splits_the_step():
    scenario, source = make("two_lane", ["gradients=analytic"])[:2]
    z = scenario.make_world(0).z
    z[0, 1], z[0, 2] = 1.6, 0.15  # nudged towards the platoon, so the safety constraints are active
    states = [PlanningState("two_lane", mpc.Observation(z[0].copy(), np.zeros(2), backfill(z, 8, 0.2)), None)]
    solver_step()(settings("two_lane"), states[0].obs, source, None)  # first-call costs (imports, set-ups) stay out
    t0 = time.perf_counter()
    ms, calls = step_time.profile(solver_step(), source, settings, states)  # the ADMM loop run from Python
    wall_ms = 1e3 * (time.perf_counter() - t0)
    assert calls["DAQP solves"] > 0 and calls["DAQP solves"] == calls["DAQP solves called from Python"]
    assert "onnxruntime calls" not in calls and "OSQP solves" not in calls and ms["compiled kernels (numba)"] > 0
    assert 0.3 * wall_ms < sum(ms.values()) <= wall_ms
    assert any(k.startswith("planner/") for k in ms)
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
    monkeypatch.setattr(safety, "compiled_params", lambda source: None)
    _, driven = step_time.profile(solver_step(), source, lambda scenario: s, states)
    assert "one-call ADMM solves" not in driven and calls["DAQP solves"] == driven["DAQP solves called from Python"] > 0


def test_profile_splits_a_known_step_per_state():
    def step(s, obs, src, warm):  # stands in for an MPC step: 10 ms in a C function (sleep), then a little own Python
        time.sleep(0.010)
        return sum(range(1000))

    ms, calls = step_time.profile(step, None, lambda scenario: None, [PlanningState("two_lane", None, None)] * 10)
    assert set(ms) == {"numpy / builtins", "tests/test_bench_profile.py"} and calls == {}
    # per step, not summed over the 10 states (100 ms); sleep can only overrun, by a loaded machine's scheduling too
    assert 10.0 <= ms["numpy / builtins"] < 50.0
    assert ms["tests/test_bench_profile.py"] < 5.0


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
