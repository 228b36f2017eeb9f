"""Accuracy where the planner uses it, and speed: composed d b_i / d Z on held-out planning states, microseconds per call.

Every Jacobian source is composed with the same rollout values (the source predictor's phi), so the figures measure
the gradient alone. The direct term of d b_i / d Z (the ego's own xy) is exact for every source; the `react_*`
figures isolate what the predictor contributes, d p_i / d Z of the other cars.
"""
import time

import numpy as np

from distill.rollout import rollout_jacobian


def dZ(phi, jac, history, ego_future, R):
    """d b_i / d Z (N*T_p, 4*T_p) m^2/m and d p_i / d ego xy (T_p, N, 2, T_p, 2), values from phi, local Jacobians from jac."""
    from planner.safety import b_i_jacobian  # the planner's eq. (8) derivative, reused so both measure the same thing

    values, grads = rollout_jacobian(lambda w: (phi(w), jac(w)), history, ego_future)
    return b_i_jacobian(values, grads, R)[1], grads[:, 1:]


def cosine(a, b):
    """Cosine similarity of two arrays, flattened."""
    return float(np.vdot(a, b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-300))


def relative(a, b):
    """||a - b|| / ||b||, flattened."""
    return float(np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-300))


def gradient_accuracy(source, jacs: dict, histories, ego_futures, R):
    """Per Jacobian source name: grad_cosine, grad_rel_err, react_cosine, react_rel_err, means over the states."""
    scores = {name: {"grad_cosine": [], "grad_rel_err": [], "react_cosine": [], "react_rel_err": []} for name in jacs}
    exact = lambda w: source.phi_jac(w)[1]  # noqa: E731  (the source's own exact local Jacobian)
    for history, ego_future in zip(histories, ego_futures):
        G, react = dZ(source.phi, exact, history, ego_future, R)
        for name, jac in jacs.items():
            G_hat, react_hat = dZ(source.phi, jac, history, ego_future, R)
            s = scores[name]
            s["grad_cosine"].append(cosine(G_hat, G))
            s["grad_rel_err"].append(relative(G_hat, G))
            s["react_cosine"].append(cosine(react_hat, react))
            s["react_rel_err"].append(relative(react_hat, react))
    return {name: {k: float(np.mean(v)) for k, v in s.items()} for name, s in scores.items()}


def time_us(fn, arg, repeats=200):
    """Median wall time of fn(arg) in microseconds, after a warm-up."""
    for _ in range(10):
        fn(arg)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn(arg)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e6)
