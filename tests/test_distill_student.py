"""The student's exact Jacobian, its certificate against sampled gradients and Hessians, a violated bound caught, and
Theorem 1's matrix terms against the dynamics built here."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from torch.func import jacrev

from conftest import compose_cfg
from core.jobs import UserError
from data import dataset
from data.bicycle import linearize, step
from distill import certificate
from distill.models import StudentPredictor, TorchPredictor
from distill.perturb import box_windows, planner_like

STUDENT = compose_cfg("distill", ["model=student"]).model
CERT = OmegaConf.to_container(STUDENT.certificate, resolve=True)
BOX = CERT["box"]
PARAMS = instantiate(compose_cfg("make_dataset", ["scenario=two_lane"]).scenario.params)  # the bicycle Theorem 1 linearises


def gelu_student(hidden):
    """A GeluStudent configured as the job's, with other hidden widths."""
    return instantiate(STUDENT.net, hidden=list(hidden))


@pytest.fixture(scope="module")
def student():
    """A student with random, clearly nonlinear weights (the head is not near zero)."""
    torch.manual_seed(0)
    net = gelu_student((32, 32))
    torch.nn.init.normal_(net.layers[-1].weight, std=0.5)
    return StudentPredictor(net)


@pytest.fixture(scope="module")
def windows(tiny_dataset):
    """Dataset windows, planner-like perturbations and random box windows (metres, ego-centred)."""
    rng = np.random.default_rng(0)
    X = dataset.load(tiny_dataset, "test")["X"][:200].astype(float)
    X = X - X[:, -1:, :1]
    return np.concatenate([X, planner_like(X, rng, **STUDENT.data.perturb), box_windows(200, rng, BOX)])


def test_student_jacobian_matches_autodiff_and_finite_differences(student, windows):
    w = windows[::10]
    nxt, J = student.phi_jac(w)
    assert np.array_equal(student.phi(w), nxt)  # the values-only pass is the same arithmetic
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
    net = gelu_student((32, 32))
    net.load_state_dict(student.module.state_dict())
    with torch.no_grad():
        net.layers[1].weight.mul_(40.0)
    changed = StudentPredictor(net)
    emp2 = certificate.sampled(TorchPredictor("student", net).phi_jac,
                               lambda w: changed.jac_cols(w, certificate.ego_columns()), windows)
    with pytest.raises(UserError, match="certificate violated"):
        certificate.verify(cert, emp2)


def test_rho_bound_matrix_terms_match_the_linearised_dynamics():
    """sigma_min(C) and M from A, B, C assembled here block by block and checked to encode the linearised bicycle."""
    t_p, typ = CERT["T_p"], CERT["typical"]
    z0 = np.array([0.0, 0.0, 0.0, typ["v"]])
    p = PARAMS
    A_t, B_t, C_t, D_t = linearize(z0, typ["delta"], typ["a"], p)
    A, B, C = np.zeros((4 * t_p, t_p)), np.zeros((4 * t_p, t_p)), np.zeros((4 * t_p, 4 * t_p))
    for k in range(t_p):  # row block k: -z_{k+1} + C~ z_k + A~ delta_k + B~ a_k + D~ = 0, z_0 given
        A[4 * k : 4 * k + 4, k], B[4 * k : 4 * k + 4, k] = A_t, B_t
        C[4 * k : 4 * k + 4, 4 * k : 4 * k + 4] = -np.eye(4)
        if k:
            C[4 * k : 4 * k + 4, 4 * k - 4 : 4 * k] = C_t
    rng = np.random.default_rng(0)
    delta, a = rng.normal(0, 0.01, t_p), rng.normal(0, 0.1, t_p)
    Z, z = [], z0
    for k in range(t_p):  # small inputs about the linearisation point: the bicycle itself, to first order
        z = step(z, [delta[k], a[k]], p)
        Z.append(z)
    c_Z = -np.concatenate([C_t @ z0 + D_t] + [D_t] * (t_p - 1))
    assert np.abs(A @ delta + B @ a + C @ np.concatenate(Z) - c_Z).max() < 1e-3
    r = certificate.rho_bound({"s_x": 63.0, "s_y": 12.85, "theta_x": 0.1, "theta_y": 0.05, "L": 0.2}, BOX, CERT["cost"],
                              t_p, lambda_s=CERT["lambda_s"], params=p, **typ)
    sigma_C = np.linalg.svd(C, compute_uv=False).min()  # C is square with a unit diagonal: full rank
    assert r["sigma_min_C"] == pytest.approx(sigma_C, rel=1e-9)
    # A and B have one column per step on disjoint rows: their singular values are ||A~|| and ||B~|| = dt
    assert r["M"] == pytest.approx(max(1 / np.linalg.norm(A_t), 1 / p.dt, 1 / sigma_C), rel=1e-9)


def test_rho_bound_grows_with_the_certified_constants():
    c = {"s_x": 63.0, "s_y": 12.85, "theta_x": 0.1, "theta_y": 0.05, "L": 0.2}
    bound = lambda **k: certificate.rho_bound({**c, **k}, BOX, CERT["cost"], CERT["T_p"], lambda_s=CERT["lambda_s"],
                                              params=PARAMS, **CERT["typical"])
    r = bound()
    assert r["rho_bound"] > 1.0
    assert bound(L=0.4)["L_J"] > r["L_J"] and bound(L=0.4)["rho_bound"] > r["rho_bound"]
    assert bound(theta_x=0.2)["rho_bound"] > r["rho_bound"] and bound(theta_y=0.1)["rho_bound"] > r["rho_bound"]
