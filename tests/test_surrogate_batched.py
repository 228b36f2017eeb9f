"""The surrogate source's fast path: a fused export's two halves (the source's forward pass, the learned J) give the
fused graph's outputs, one J call for a whole rollout gives the per-window chain rule's values and derivative, a
batch of plans gives each plan's values, the memo of windows holds one step's and computes each distinct window of a
batch once, and the teacher's compiled forward pass is the torch network's (speed: `make bench`)."""
import copy

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from test_surrogate import smooth_student

from bench.states import collect
from conftest import compose_cfg
from core.rollout import SLOTS, T_OBS, ego_xy, rollout, rollout_jacobian
from distill.models import StudentPredictor, TorchPredictor
from planner.gradients import Surrogate
from surrogate import kernels, models
from surrogate.export import export
from surrogate.network import Fused, JacobianNet


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A random-weight JacobianNet fused with a smooth student as the source, exported and loaded as the planner does."""
    folder = tmp_path_factory.mktemp("fused")
    torch.manual_seed(1)
    net = JacobianNet(T_OBS, SLOTS, 16, 1, "").eval()
    export(Fused(copy.deepcopy(net), smooth_student()), folder / "surrogate.onnx", T_OBS, SLOTS, "student")
    return models.load(folder, T_OBS, SLOTS - 1)


@pytest.fixture(scope="module")
def states():
    """(history, ego plan) of planning states of a closed-loop two_lane run (analytic predictor), at their warm plans."""
    return [(st.obs.history, ego_xy(st.warm.Z, 8)) for st in collect(scenarios=("two_lane",), per_scenario=6)
            if st.warm is not None]


def counted(surrogate, monkeypatch):
    """{output: [batch sizes]} of the onnxruntime calls each half of `surrogate` gets from now on."""
    calls = {"next": [], "J": []}
    for out, session in surrogate.halves.items():
        run = session.run
        monkeypatch.setattr(session, "run", lambda names, feed, run=run, out=out: calls[out].append(len(feed["window"]))
                            or run(names, feed), raising=False)
    return calls


def test_the_halves_give_the_fused_graphs_outputs(exported, states):
    windows = np.stack([h for h, _ in states])
    nxt, J = exported.phi_jac(windows)
    assert np.array_equal(exported.phi(windows), nxt) and np.array_equal(exported.jac(windows), J)
    assert np.array_equal(np.concatenate([exported.jac(w[None]) for w in windows]), J)  # a batch is its rows


def test_one_j_call_per_rollout_gives_the_per_window_chain_rule(exported, states, monkeypatch):
    source = Surrogate("surrogate", None, exported)
    calls = counted(exported, monkeypatch)
    for history, ego in states:
        want = rollout_jacobian(exported.phi_jac, history, ego)  # the fused call per window, core.rollout's chain rule
        before = {k: len(v) for k, v in calls.items()}
        values, grads = source.jacobian(history, ego)
        assert np.abs(grads[:, 1:]).max() > 1e-3  # the others respond to the ego plan
        np.testing.assert_allclose(values, want[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(grads, want[1], rtol=0, atol=1e-9)
        assert calls["J"][before["J"]:] == [len(ego) - 1]  # every window after the observed one, at once
        assert len(calls["next"]) - before["next"] <= len(ego)  # at most one forward pass per step of the plan
        again = len(calls["next"])
        np.testing.assert_array_equal(source.jacobian(history, ego)[1], grads)
        assert len(calls["next"]) == again  # the same plan again: its windows are known, no forward pass


def test_the_memo_keeps_one_step_and_batches_equal_single_plans(exported, states):
    source, fresh = Surrogate("surrogate", None, exported), Surrogate("surrogate", None, exported)
    (h1, ego), (h2, _) = states[0], states[1]
    source.values(h1, ego[None])
    source.values(h1, ego[None] + 0.2)
    np.testing.assert_array_equal(source.values(h2, ego[None]), fresh.values(h2, ego[None]))
    assert len(source.seen[1]) == len(ego)  # h2's windows only: a closed loop's memo does not grow step by step
    plans = np.stack([ego, ego + 0.5, ego - 0.3])
    batch = source.values(h1, plans)
    single = np.stack([fresh.values(h1, p[None])[0] for p in plans])
    np.testing.assert_allclose(batch, single, rtol=0, atol=1e-9)
    assert np.abs(batch[1] - batch[0])[:, 1:].max() > 1e-2  # the others respond: the plans are not one


def test_a_closed_loop_batch_computes_each_distinct_window_once_and_equals_one_candidate_at_a_time(exported, states):
    source = Surrogate("surrogate", None, exported)
    calls, forward = [], source.forward
    source.forward = lambda w: calls.append(len(w)) or forward(w)
    history, _ = states[0]
    steps = np.array([[1.0, 0.0], [1.0, 0.0], [1.2, 0.05]])  # m a step: the first two candidates are one policy
    policy = lambda window, tau, steps=steps: window[:, -1, 0] + steps * (1 + 0.1 * tau)
    T = 6
    batch = source.react(history, policy, T, len(steps))
    single = [Surrogate("surrogate", None, exported).react(history, lambda w, tau, s=s: policy(w, tau, s[None]), T, 1)[0]
              for s in steps]
    np.testing.assert_allclose(batch, np.stack(single), rtol=0, atol=1e-9)
    assert calls == [1] + [2] * (T - 1)  # the shared observed window once, then each distinct policy's window once
    assert np.abs(batch[2] - batch[0])[:, 1:].max() > 1e-3  # the others respond: the policies are not one


def test_the_compiled_teacher_is_the_torch_network_to_float32_rounding(exported, states):
    """A small random-weight SocialTeacher whose decoder responds (its last layer starts at zero, constant velocity)."""
    torch.manual_seed(2)
    net = instantiate(compose_cfg("distill", ["model=teacher"]).model.net, hidden=8, pool=8, decoder=[16, 16])
    torch.nn.init.normal_(net.decoder[-1].weight, 0.0, 0.5)
    teacher = TorchPredictor("teacher", net.eval())
    phi = kernels.compiled_phi(teacher)
    assert kernels.compiled_phi(TorchPredictor("student", smooth_student())) is None  # only the teacher's network
    windows = np.stack([h for h, _ in states])
    want = teacher.phi(windows)
    assert np.abs(want - (2 * windows[:, -1] - windows[:, -2]))[:, 1:].max() > 1e-3  # the others are not at cv
    np.testing.assert_allclose(phi(windows), want, rtol=0, atol=1e-5)  # float32 at tens of metres: ~4e-6 m apart
    source = Surrogate("surrogate", teacher, exported)  # the teacher's values, the export's J
    history, ego = states[0]
    np.testing.assert_allclose(source.values(history, ego[None]), rollout(teacher.phi, history[None], ego[None]),
                               rtol=0, atol=1e-5)


def test_a_batch_of_new_windows_goes_to_the_export_only_when_it_is_the_teachers_network(exported, states, tmp_path,
                                                                                        monkeypatch):
    """From BATCHED new windows on, the teacher's values come from one onnxruntime call of a fused export of the same
    network, equal to the kernel's to float32 rounding; an export made from another network (here the student's) is
    never asked for values after the check that tells them apart."""
    from planner.gradients import BATCHED

    torch.manual_seed(3)
    net = instantiate(compose_cfg("distill", ["model=teacher"]).model.net, hidden=8, pool=8, decoder=[16, 16]).eval()
    torch.nn.init.normal_(net.decoder[-1].weight, 0.0, 0.5)
    teacher = TorchPredictor("teacher", net)
    export(Fused(JacobianNet(T_OBS, SLOTS, 16, 1, "").eval(), net), tmp_path / "surrogate.onnx", T_OBS, SLOTS, "teacher")
    own = models.load(tmp_path, T_OBS, SLOTS - 1)
    history, _ = states[0]
    plans = np.stack([ego for _, ego in states[:BATCHED]])
    want = rollout(teacher.phi, np.broadcast_to(history, (BATCHED, *history.shape)), plans)
    for surrogate, asked in ((own, True), (exported, False)):
        source = Surrogate("surrogate", teacher, surrogate)
        calls = counted(surrogate, monkeypatch)
        np.testing.assert_allclose(source.values(history, plans), want, rtol=0, atol=1e-5)
        assert calls["next"] == ([BATCHED] * (plans.shape[1] - 1) if asked else [])  # the shared first window: the kernel


def test_over_another_predictor_the_values_are_that_predictors_and_the_jacobians_the_exports(exported, states, monkeypatch):
    """The planner's default pairing: the surrogate's learned J with the student's values. The fused export's forward
    pass (another network) is never called; the values are the student's own rollout, and d values / d ego the
    export's J at that rollout's windows, composed by the chain rule."""
    student = StudentPredictor(smooth_student(seed=3))
    source = Surrogate("surrogate", student, exported)
    assert not source.joint  # the export's values are not this predictor's
    calls = counted(exported, monkeypatch)
    for history, ego in states[:3]:
        want = rollout_jacobian(lambda w: (student.phi(w), exported.jac(w)), history, ego)
        values, grads = source.jacobian(history, ego)
        plans = np.stack([ego, ego + 0.5])
        own = rollout(student.phi, np.stack([history, history]), plans)  # the student's rollouts in numpy
        np.testing.assert_allclose(values, own[0], rtol=0, atol=1e-9)
        np.testing.assert_allclose(grads, want[1], rtol=0, atol=1e-9)
        np.testing.assert_allclose(source.values(history, plans), own, rtol=0, atol=1e-9)
    assert calls["next"] == []
