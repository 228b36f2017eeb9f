"""The student: a small GELU MLP with a bounded head, built so that the paper's A1-A3 hold with computable constants.

phi(window) = last + (last - previous) + s * tanh(W_L h(P window))  for the other cars, constant velocity for the ego.
P is a fixed linear map from the window in metres to translation-invariant, scaled features (positions relative to
the ego's last position, last velocities, all accelerations); being linear it folds into the first layer, so the
certificate is in metres. GELU is C^2 and tanh bounds the acceleration term by s (metres per step), hence A1-A3.
"""
import numpy as np
import torch
from torch import nn

from core.rollout import SLOTS, T_OBS


def feature_map(pos_scale, vel_scale, acc_scale):
    """P (78, 80): window flattened (T_obs, SLOTS, 2) in metres -> scaled relative positions, velocities, accelerations."""
    def at(t, i, c):
        """The window-shaped indicator of coordinate c of slot i at time t."""
        e = np.zeros((T_OBS, SLOTS, 2))
        e[t, i, c] = 1.0
        return e

    rows = []
    for i in range(1, SLOTS):  # others' last position relative to the ego's last position
        for c in range(2):
            rows.append((at(-1, i, c) - at(-1, 0, c)) / pos_scale)
    for i in range(SLOTS):  # last velocity (m per step)
        for c in range(2):
            rows.append((at(-1, i, c) - at(-2, i, c)) / vel_scale)
    for t in range(2, T_OBS):  # every acceleration (m per step^2)
        for i in range(SLOTS):
            for c in range(2):
                rows.append((at(t, i, c) - 2 * at(t - 1, i, c) + at(t - 2, i, c)) / acc_scale)
    return np.stack([r.reshape(-1) for r in rows])


class GeluStudent(nn.Module):
    """GELU MLP on P window with a bounded acceleration head s * tanh (s in metres per step^2, per x and y)."""

    def __init__(self, hidden, s_acc, pos_scale, vel_scale, acc_scale):
        """Hidden widths, head bound s_acc (m per step^2, x and y), feature scales (m, m/step, m/step^2)."""
        super().__init__()
        P = torch.tensor(feature_map(pos_scale, vel_scale, acc_scale), dtype=torch.float32)
        self.register_buffer("P", P)
        self.register_buffer("s", torch.tensor(list(s_acc) * (SLOTS - 1), dtype=torch.float32))
        sizes = [P.shape[0], *hidden, 2 * (SLOTS - 1)]
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))
        nn.init.normal_(self.layers[-1].weight, std=1e-3)  # start near constant velocity (not 0: log ||W|| penalty)
        nn.init.zeros_(self.layers[-1].bias)

    def forward(self, window):
        """Next xy (B, SLOTS, 2) in metres from window (B, T_obs, SLOTS, 2) in metres."""
        b = window.shape[0]
        h = window.reshape(b, -1) @ self.P.T
        for layer in self.layers[:-1]:
            h = nn.functional.gelu(layer(h))
        acc = (self.s * torch.tanh(self.layers[-1](h))).reshape(b, SLOTS - 1, 2)
        cv = 2.0 * window[:, -1] - window[:, -2]
        return torch.cat([cv[:, :1], cv[:, 1:] + acc], dim=1)

    def weights64(self):
        """[(W, b)] per layer in float64 numpy, the first with P folded in (so it acts on the window in metres)."""
        out = []
        for k, layer in enumerate(self.layers):
            W = layer.weight.detach().double().numpy()
            if k == 0:
                W = W @ self.P.double().numpy()
            out.append((W, layer.bias.detach().double().numpy()))
        return out


def _gelu(a, derivative=True):
    """Exact GELU and, with `derivative`, its derivative (else None), float64 numpy (matches torch's default erf form)."""
    from scipy.special import erf

    cdf = 0.5 * (1.0 + erf(a / np.sqrt(2.0)))
    if not derivative:  # a rollout's values: the derivative's exp was a sixth of a forward pass
        return a * cdf, None
    pdf = np.exp(-0.5 * a * a) / np.sqrt(2.0 * np.pi)
    return a * cdf, cdf + a * pdf


def phi_jac64(weights, s, window, jac=True, cols=None):
    """The student in float64 numpy: next (B, SLOTS, 2) in metres and, if jac, its exact Jacobian (B, SLOTS*2, T_obs*SLOTS*2).

    cols restricts the Jacobian to those input columns (cheaper when only the ego's inputs matter).
    """
    cols = np.arange(T_OBS * SLOTS * 2) if cols is None else np.asarray(cols)
    window = np.asarray(window, dtype=float)
    b = window.shape[0]
    h = window.reshape(b, -1)
    grad = None
    for W, bias in weights[:-1]:
        a = h @ W.T + bias
        h, dh = _gelu(a, jac)
        if jac:  # the values alone skip the chain: most of the cost
            grad = dh[:, :, None] * (W[:, cols] if grad is None else W @ grad)  # d h / d window[cols], (B, width, cols)
    W, bias = weights[-1]
    t = np.tanh(h @ W.T + bias)
    cv = 2.0 * window[:, -1] - window[:, -2]
    nxt = cv.copy()
    nxt[:, 1:] += (s * t).reshape(b, SLOTS - 1, 2)
    if not jac:
        return nxt
    J_cv = np.zeros((SLOTS * 2, T_OBS * SLOTS * 2))
    J_cv[:, -SLOTS * 2:] = 2.0 * np.eye(SLOTS * 2)
    J_cv[:, -2 * SLOTS * 2:-SLOTS * 2] = -np.eye(SLOTS * 2)
    J = np.repeat(J_cv[None, :, cols], b, axis=0)
    J[:, 2:] += (s * (1.0 - t * t))[:, :, None] * (W @ grad)
    return nxt, J
