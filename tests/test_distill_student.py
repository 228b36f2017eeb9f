"""The student's exact Jacobian, its certificate against sampled gradients and Hessians, and a violated bound caught."""
import numpy as np
import pytest
import torch
from torch.func import jacrev

from core.jobs import UserError
from data import dataset
from distill import certificate
from distill.models import StudentPredictor, TorchPredictor
from distill.perturb import box_windows, planner_like
from distill.student import GeluStudent

BOX = {"x": 60.0, "y": 12.0, "dx": 2.5, "dy": 0.6}


@pytest.fixture(scope="module")
def student():
    """A student with random, clearly nonlinear weights (the head is not near zero)."""
    torch.manual_seed(0)
    net = GeluStudent(hidden=(32, 32))
    torch.nn.init.normal_(net.layers[-1].weight, std=0.5)
    return StudentPredictor(net)


@pytest.fixture(scope="module")
def windows(tiny_dataset):
    """Dataset windows, planner-like perturbations and random box windows (metres, ego-centred)."""
    rng = np.random.default_rng(0)
    X = dataset.load(tiny_dataset, "test")["X"][:200].astype(float)
    X = X - X[:, -1:, :1]
    return np.concatenate([X, planner_like(X, rng), box_windows(200, rng, BOX)])


def test_student_jacobian_matches_autodiff_and_finite_differences(student, windows):
    w = windows[::10]
    nxt, J = student.phi_jac(w)
    net64 = student.module.double()
    try:
        J_auto = jacrev(lambda x: net64(x).sum(0))(torch.tensor(w)).reshape(10, len(w), -1).permute(1, 0, 2).detach().numpy()
        assert np.allclose(nxt, net64(torch.tensor(w)).detach().numpy(), atol=1e-9)
    finally:
        student.module.float()
    assert np.allclose(J, J_auto, atol=1e-9)
    h = 1e-5
    J_fd = np.zeros_like(J)
    for c in range(w[0].size):
        e = np.zeros(w[0].size)
        e[c] = h
        e = e.reshape(w.shape[1:])
        J_fd[:, :, c] = ((student.phi(w + e) - student.phi(w - e)) / (2 * h)).reshape(len(w), -1)
    assert np.abs(J - J_fd).max() < 1e-6
    assert np.abs(J[:, 2:]).max() > 0.1  # the check is not vacuous: the network part is present


def test_certificate_bounds_sampled_gradients_and_hessians(student, windows):
    cert = certificate.constants(student.weights, student.s, BOX)
    emp = certificate.sampled(TorchPredictor("student", student.module).phi_jac,
                              lambda w: student.jac_cols(w, certificate.ego_columns()), windows)
    certificate.verify(cert, emp)
    r = certificate.ratios(cert, emp)
    assert all(0.0 < v <= 1.0 for v in r.values()), r
    # A1: outputs stay within s_x, s_y on box windows
    out = student.phi(box_windows(500, np.random.default_rng(1), BOX))
    assert np.abs(out[:, 1:, 0]).max() <= cert["s_x"] and np.abs(out[:, 1:, 1]).max() <= cert["s_y"]


def test_violated_bound_fails_the_check(student, windows):
    cert = certificate.constants(student.weights, student.s, BOX)
    emp = certificate.sampled(TorchPredictor("student", student.module).phi_jac,
                              lambda w: student.jac_cols(w, certificate.ego_columns()), windows)
    too_small = {**cert, "L": 0.5 * emp["emp_L_max"]}
    with pytest.raises(UserError, match="ratio_L"):
        certificate.verify(too_small, emp)
    # weights changed after certification: the old certificate no longer holds on samples
    net = GeluStudent(hidden=(32, 32))
    net.load_state_dict(student.module.state_dict())
    with torch.no_grad():
        net.layers[1].weight.mul_(40.0)
    changed = StudentPredictor(net)
    emp2 = certificate.sampled(TorchPredictor("student", net).phi_jac,
                               lambda w: changed.jac_cols(w, certificate.ego_columns()), windows)
    with pytest.raises(UserError, match="certificate violated"):
        certificate.verify(cert, emp2)


def test_rho_bound_follows_theorem_1():
    c = {"s_x": 63.0, "s_y": 12.85, "theta_x": 0.1, "theta_y": 0.05, "L": 0.2}
    cost = {"lambda_div": 1.0, "lambda_v": 1.0, "lambda_delta": 0.6, "lambda_a": 0.4, "lambda_ddelta": 0.4, "lambda_da": 0.2}
    r = certificate.rho_bound(c, BOX, cost)
    assert r["L_2"] == pytest.approx(2.2) and r["L_3"] == pytest.approx(2.1)
    assert r["L_g"] == pytest.approx(8 * 2 * r["L_1"])
    assert r["M"] >= 5.0  # B has one dt = 0.2 per column, so 1 / sigma_min(B) = 5
    assert r["rho_bound"] == pytest.approx((1 + 2 * r["sigma_min_C"]) * r["L_J"] * r["M"])
    assert certificate.rho_bound({**c, "L": 0.4}, BOX, cost)["rho_bound"] > r["rho_bound"]
