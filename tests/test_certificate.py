"""Region certificate of a small random GELU student: interval bounds contain sampled pre-activations, the region's
theta and L bound autodiff gradients and finite-difference Hessians at corners and inside, and never exceed the global."""
import numpy as np
import pytest
import torch

from core.jobs import UserError
from distill import certificate
from distill.models import StudentPredictor, TorchPredictor
from distill.student import GeluStudent

REGION = {"rel_x": [-8.0, 12.0], "rel_y": [-1.0, 5.0], "vel_x": [0.8, 1.2], "vel_y": [-0.05, 0.1],
          "acc_x": [-0.004, 0.004], "acc_y": [-0.002, 0.003]}
BOX = {"x": 60.0, "y": 12.0, "dx": 2.5, "dy": 0.6}


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
