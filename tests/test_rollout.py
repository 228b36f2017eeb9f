"""The Remark 2 recursion and its chain rule: composed Jacobians equal autograd through the whole rollout."""
import numpy as np
import torch

from core.rollout import SLOTS, T_OBS, react, rollout, rollout_jacobian
from distill.predictors import ConstantVelocity

T_P = 8


def history(seed=0):
    rng = np.random.default_rng(seed)
    start = np.array([[0.0, 0.0], [12.0, 4.0], [5.0, 4.0], [-2.0, 4.0], [-9.0, 4.0]]) + rng.normal(0, 0.3, (SLOTS, 2))
    vel = np.array([1.0, 0.0]) + rng.normal(0, 0.05, (SLOTS, 2))
    return start[None] + np.arange(T_OBS)[:, None, None] * vel[None]


class SmoothNet(torch.nn.Module):
    """A random smooth interactive predictor: next = last + small GELU-MLP displacement of the relative window."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.net = torch.nn.Sequential(torch.nn.Linear(T_OBS * SLOTS * 2, 64), torch.nn.GELU(), torch.nn.Linear(64, SLOTS * 2))

    def forward(self, window):
        rel = window - window[:, -1:, :1]
        return window[:, -1] + 0.3 * torch.tanh(self.net(rel.flatten(1))).view(-1, SLOTS, 2)


def test_rollout_fills_the_ego_slot_from_the_plan_and_shifts_the_window():
    h = history()
    ego = h[-1, 0] + np.arange(1, T_P + 1)[:, None] * np.array([1.2, 0.3])
    out = rollout(ConstantVelocity().phi, h[None], ego[None])[0]
    np.testing.assert_allclose(out[:, 0], ego)
    vel = h[-1, 1:] - h[-2, 1:]
    np.testing.assert_allclose(out[:, 1:], h[-1, 1:][None] + np.arange(1, T_P + 1)[:, None, None] * vel[None])


def test_composed_jacobian_equals_autograd_through_the_rollout():
    net = SmoothNet().double()
    h = history(1)
    ego = h[-1, 0] + np.arange(1, T_P + 1)[:, None] * np.array([1.0, 0.4])

    def phi_jac(window):
        w = torch.tensor(window)
        J = torch.func.jacrev(lambda x: net(x[None])[0])(w[0])
        return net(w).detach().numpy(), J.reshape(1, SLOTS * 2, -1).detach().numpy()

    values, grads = rollout_jacobian(phi_jac, h, ego)
    full = torch.func.jacrev(lambda e: rollout(net, torch.tensor(h)[None], e[None])[0])(torch.tensor(ego)).detach()
    ref = rollout(net, torch.tensor(h)[None], torch.tensor(ego)[None])[0].detach().numpy()
    np.testing.assert_allclose(values, ref, atol=1e-12)
    assert np.abs(full.numpy()).max() > 0.01  # the net does react to the ego plan
    np.testing.assert_allclose(grads, full.numpy(), rtol=1e-5, atol=1e-5 * np.abs(full.numpy()).max())


def test_constant_velocity_rollout_does_not_react_to_the_plan():
    h = history(2)
    ego = h[-1, 0] + np.arange(1, T_P + 1)[:, None] * np.array([1.0, 0.0])
    _, grads = rollout_jacobian(ConstantVelocity().phi_jac, h, ego)
    assert np.abs(grads[:, 1:]).max() == 0.0
    np.testing.assert_array_equal(grads[:, 0].reshape(T_P, 2, T_P, 2), np.einsum("ab,ij->aibj", np.eye(T_P), np.eye(2)))


def test_a_feedback_policy_answers_the_predicted_window_of_its_own_step():
    """react hands the ego's policy the window ending at step tau, the others as predicted: an ego told to sit 3 m
    behind car 2's last position (SmoothNet moves it) is there one step later, every step, for every batch member."""
    net, hist = SmoothNet(), torch.as_tensor(np.stack([history(0), history(1)]), dtype=torch.float64)
    net.double()
    seen = []

    def behind(window, tau):
        seen.append(tau)
        return window[:, -1, 2] - torch.tensor([3.0, 0.0], dtype=torch.float64)

    with torch.no_grad():
        out = react(net, hist, behind, T_P)
    assert seen == list(range(T_P)) and out.shape == (2, T_P, SLOTS, 2)
    previous = torch.cat([hist[:, -1:, 2], out[:, :-1, 2]], dim=1)  # car 2 at steps 0..T_P-1
    assert torch.allclose(out[:, :, 0], previous - torch.tensor([3.0, 0.0], dtype=torch.float64))
    fixed = out[:, :, 0].clone()  # replayed as a plan fixed in advance, the recursion gives the same rollout
    with torch.no_grad():
        assert torch.allclose(rollout(net, hist, fixed), out)

