"""Region certificate of a small random GELU student: interval bounds contain sampled pre-activations, the region's
theta and L bound autodiff gradients and finite-difference Hessians at corners and inside, and never exceed the global."""
import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import BOX, REGION, compose_cfg
from core.jobs import UserError, options
from data.bicycle import linearize
from distill import certificate
from distill.models import StudentPredictor, TorchPredictor
from distill.student import GeluStudent
from distill.train import scenario_configs


@pytest.fixture(scope="module")
def student():
    """A random two-layer GELU student whose head is far from linear (large last-layer weights)."""
    torch.manual_seed(0)
    net = GeluStudent([12, 10], [0.5, 0.25], pos_scale=10.0, vel_scale=0.5, acc_scale=0.05)
    torch.nn.init.normal_(net.layers[-1].weight, std=0.8)
    return StudentPredictor(net.eval())


def _check(student, windows, cert):
    emp = certificate.sampled(TorchPredictor("student", student.module).phi_jac,
                              lambda w: student.jac_cols(w, certificate.ego_columns()), windows)
    certificate.verify(cert, emp)
    return certificate.ratios(cert, emp)


def test_windows_from_features_round_trip_and_region_membership():
    rng = np.random.default_rng(1)
    lo, hi = certificate.feature_box(REGION)
    F = rng.uniform(lo, hi, (5, len(lo)))
    w = certificate.windows_from_features(F)
    assert np.allclose(w.reshape(5, -1) @ certificate.metric_features().T, F, atol=1e-9)
    assert certificate.in_region(w, lo, hi).all()
    w[:, -1, 2, 0] += 1.0  # car 1's last x moves 1 m: its relative position, velocity and acceleration change
    assert not certificate.in_region(w, lo, hi).any()


def test_interval_bounds_contain_sampled_preactivations(student):
    rng = np.random.default_rng(2)
    lo, hi = certificate.feature_box(REGION)
    Z = certificate.preactivation_bounds(student.weights, lo, hi)
    h = certificate.region_samples(lo, hi, 400, rng).reshape(400, -1)
    for (W, b), (zlo, zhi) in zip(student.weights, Z):
        z = h @ W.T + b
        assert np.all(z >= zlo - 1e-9) and np.all(z <= zhi + 1e-9)
        h = certificate._gelu(z)
    assert np.all(Z[0][1] - Z[0][0] > 0)


def test_region_bound_at_a_point_is_the_exact_gradient(student):
    w = certificate.region_samples(*certificate.feature_box(REGION), 2, np.random.default_rng(3))[1:]
    F = w.reshape(1, -1) @ certificate.metric_features().T
    c = certificate.region_constants(student.weights, student.s, F[0], F[0])
    J = student.jac_cols(w, certificate.ego_columns())[0, 2:]  # others' rows, ego columns
    assert c["theta_x"] == pytest.approx(np.abs(J[0::2]).max(), rel=1e-9)
    assert c["theta_y"] == pytest.approx(np.abs(J[1::2]).max(), rel=1e-9)


def test_region_bound_holds_at_corners_and_inside_and_beats_the_global(student):
    lo, hi = certificate.feature_box(REGION)
    region = certificate.region_constants(student.weights, student.s, lo, hi)
    glob = certificate.constants(student.weights, student.s, BOX)
    for k in ("theta_x", "theta_y", "L"):
        assert region[k] < glob[k]
    r = _check(student, certificate.region_samples(lo, hi, 600, np.random.default_rng(4)), region)
    assert r["ratio_theta_x"] > 0.1 and r["ratio_theta_y"] > 0.1 and r["ratio_L"] > 0.01  # not vacuous
    both = certificate.tightest(glob, region)
    assert all(both[k] == min(glob[k], region[k]) for k in ("theta_x", "theta_y", "L"))


def test_wide_region_bound_still_holds(student):
    wide = {**REGION, "acc_x": [-1.0, 1.0], "acc_y": [-1.0, 1.0], "vel_y": [-1.5, 1.5]}
    lo, hi = certificate.feature_box(wide)
    _check(student, certificate.region_samples(lo, hi, 600, np.random.default_rng(5)),
           certificate.region_constants(student.weights, student.s, lo, hi))


def test_too_small_region_bound_is_caught(student):
    lo, hi = certificate.feature_box(REGION)
    region = certificate.region_constants(student.weights, student.s, lo, hi)
    samples = certificate.region_samples(lo, hi, 200, np.random.default_rng(6))
    with pytest.raises(UserError, match="certificate violated"):
        _check(student, samples, {k: 0.01 * v for k, v in region.items()})


def test_bad_region_names_the_key():
    with pytest.raises(UserError, match="region: missing acc_y"):
        certificate.feature_box({k: v for k, v in REGION.items() if k != "acc_y"})
    with pytest.raises(UserError, match="low <= high"):
        certificate.feature_box({**REGION, "vel_x": [2.0, 0.0]})


def test_per_scenario_rho_bound_matches_lemma3_and_theorem1_computed_here(student):
    """Each scenario's rho bound from its own road and speed, against Lemma 3 / Theorem 1 written out by hand, A, B, C
    assembled row by row from the linearised bicycle; the two-lane region is narrower, so its bound is no larger."""
    cfg = compose_cfg("distill", ["model=student"])
    cert = OmegaConf.to_container(cfg.model.certificate, resolve=True)
    planner = compose_cfg("planner").mpc
    assert cert["planner"] == {"v_max": planner.v_box[1], "y_margin": planner.y_margin}  # the planner's own limits
    glob = certificate.constants(student.weights, student.s, cert["box"])
    scenarios = scenario_configs(cert["scenarios"])
    out = certificate.per_scenario(student.weights, student.s, glob, cert["region"], scenarios,
                                   cert["planner"], cert["cost"], cert["T_p"], cert["lambda_s"])
    assert set(out) == {"two_lane", "three_lane", "random", "dense"}
    two, three = out["two_lane"], out["three_lane"]
    assert two["region"]["rel_y"] == [-5.0, 5.0] and three["region"]["rel_y"] == [-9.0, 9.0]  # 4 m lanes, 1 m margin
    assert two["L"] <= three["L"] and two["rho_bound"] <= three["rho_bound"]
    assert out["random"]["v"] == 6.5  # the fastest ego start (platoon 5.5 m/s, ego 1 m/s above): the smallest sigma_min(C)
    assert out["random"]["rho_bound"] > three["rho_bound"]  # same region and road as three_lane, faster
    dense = out["dense"]  # two lanes as two_lane, the random merges' starts
    assert dense["region"] == two["region"] and dense["v"] == 6.5 and dense["rho_bound"] > two["rho_bound"]
    params = instantiate(scenarios["two_lane"]["params"])  # the bicycle as the planner builds it for two_lane
    t_p, dt, v, cost = cert["T_p"], params.dt, 5.0, cert["cost"]
    x_max, y_max = 10.0 * t_p * dt, 4.0 + 2 * 1.0
    s_x, s_y = x_max + 40.0 + 2.0 + 0.5, y_max + 5.0 + 1.53 + 0.25
    tx, ty, L = two["theta_x"], two["theta_y"], two["L"]
    L1 = 2 * (tx * (1 + tx) + ty * (1 + ty) + (x_max + y_max + s_x + s_y) * L)
    L_g = t_p * (max(L1, 2 * (1 + tx)) + max(L1, 2 * (1 + ty)))
    L_J = 2 * max(cost["lambda_div"], cost["lambda_v"]) + 4 * t_p * cert["lambda_s"] * L_g  # Z's block: 4 others
    assert L_J > 2 * (cost["lambda_delta"] + 4 * cost["lambda_ddelta"] + cost["lambda_a"] + 4 * cost["lambda_da"])
    A_t, B_t, C_t, _ = linearize(np.array([0.0, 0.0, 0.0, v]), 0.0, 0.0, params)
    A, B, C = np.zeros((4 * t_p, t_p)), np.zeros((4 * t_p, t_p)), -np.eye(4 * t_p)
    for k in range(t_p):
        A[4 * k:4 * k + 4, k], B[4 * k:4 * k + 4, k] = A_t, B_t
        if k:
            C[4 * k:4 * k + 4, 4 * k - 4:4 * k] = C_t
    sv = lambda X: np.linalg.svd(X, compute_uv=False).min()  # noqa: E731 (all three have full column rank)
    M = max(1 / sv(A), 1 / sv(B), 1 / sv(C))
    assert two["L_J"] == pytest.approx(L_J, rel=1e-9)  # above the Delta and alpha blocks' (||D'D|| < 4), so the max
    assert two["M"] == pytest.approx(M, rel=1e-9) and two["sigma_min_C"] == pytest.approx(sv(C), rel=1e-9)
    assert two["rho_bound"] == pytest.approx((1 + 2 * sv(C)) * two["L_J"] * M, rel=1e-9)


def test_training_penalty_is_the_global_certificates_L(student):
    """StudentTask.certified_L (torch, differentiable) is distill.certificate.constants' L of the same weights."""
    from distill.tasks import StudentTask

    task = StudentTask({"_target_": "torch.nn.Identity"}, 1e-3, 0.0, 0.01, 1.0, 1.0, 0.0, cert_weight=1.0, rollout_weight=0.0,
                       contrast_weight=0.0, rollout_scale_m=0.1)
    task.net = student.module
    L = task.certified_L()
    assert float(L.detach()) == pytest.approx(certificate.constants(student.weights, student.s, BOX)["L"], rel=1e-5)
    L.log().backward()
    assert student.module.layers[0].weight.grad.abs().max() > 0  # it trains the first layer's ego columns


def test_unknown_scenario_names_the_key():
    with pytest.raises(UserError, match="^model.certificate.scenarios: unknown scenario four_lane; choose from "
                                         + ", ".join(options("scenario")) + "$"):
        scenario_configs(["two_lane", "four_lane"])
