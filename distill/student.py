"""The student: a small GELU MLP with a bounded head, built so that the paper's A1-A3 hold with computable constants.

phi(window) = last + (last - previous) + s * tanh(W_L h(P window))  for the other cars, constant velocity for the ego.
P is a fixed linear map from the window in metres to translation-invariant, scaled features (positions relative to
the ego's last position, last velocities, all accelerations); being linear it folds into the first layer, so the
certificate is in metres. GELU is C^2 and tanh bounds the acceleration term by s (metres per step), hence A1-A3.
"""
import math

import numpy as np
import torch
from numba import njit
from numba.typed import List
from torch import nn

from core.jit_linalg import matvec
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
        return self.decode(window, window.reshape(window.shape[0], -1) @ self.P.T)

    def decode(self, window, h):
        """Next xy (B, SLOTS, 2) in metres: the MLP on the first layer's inputs h (B, d) (the features P window), its
        bounded head on the others' constant velocity."""
        b = window.shape[0]
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


class HypothesisStudent(GeluStudent):
    """The GELU student under a hypothesis per car, hyp (B, SLOTS) in {0, 1} (1: it yields to an encroaching ego; the
    ego's ignored), an input of the first layer beside P window: a fixed hypothesis only shifts that layer's bias, so the
    certificate's weight norms, and A1-A3, hold for every one. A separate GELU head gives p(yields | window) per car."""

    def __init__(self, hidden, s_acc, pos_scale, vel_scale, acc_scale, belief):
        """As GeluStudent's, and the belief head's hidden widths."""
        super().__init__(hidden, s_acc, pos_scale, vel_scale, acc_scale)
        self.layers[0] = nn.Linear(self.P.shape[0] + SLOTS - 1, hidden[0])
        sizes = [self.P.shape[0], *belief, SLOTS - 1]
        self.belief_layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(sizes[:-1], sizes[1:]))

    def forward(self, window, hyp):
        """Next xy (B, SLOTS, 2) in metres from window (B, T_obs, SLOTS, 2) in metres under hypotheses hyp (B, SLOTS)."""
        f = window.reshape(window.shape[0], -1) @ self.P.T
        return self.decode(window, torch.cat([f, hyp[:, 1:].to(f.dtype)], -1))

    def belief_logit(self, window):
        """log-odds (B, SLOTS) that each car yields to the ego, given the window (the ego's 0, meaningless)."""
        h = window.reshape(window.shape[0], -1) @ self.P.T
        for layer in self.belief_layers[:-1]:
            h = nn.functional.gelu(layer(h))
        logit = self.belief_layers[-1](h)
        return torch.cat([torch.zeros_like(logit[:, :1]), logit], 1)

    def belief(self, window):
        """p(yields | window) (B, SLOTS) per car, the ego's 0."""
        p = torch.sigmoid(self.belief_logit(window))
        return torch.cat([torch.zeros_like(p[:, :1]), p[:, 1:]], 1)

    def fixed(self, hyp) -> GeluStudent:
        """The GeluStudent this network is under the fixed hypotheses hyp (SLOTS,): the hypothesis inputs' columns folded
        into the first layer's bias, every other weight (and P) the same; what the certificate and the planner read."""
        state = {k: v for k, v in self.state_dict().items() if not k.startswith("belief_layers.")}
        W, n = state["layers.0.weight"], self.P.shape[0]
        h = torch.as_tensor(np.asarray(hyp, dtype=float)[1:], dtype=W.dtype)
        state["layers.0.weight"], state["layers.0.bias"] = W[:, :n], state["layers.0.bias"] + W[:, n:] @ h
        net = GeluStudent([layer.out_features for layer in self.layers[:-1]], self.s[:2].tolist(), 1.0, 1.0, 1.0)
        net.load_state_dict(state)  # P comes with the state: the scales given here are overwritten
        return net.eval()


def typed(arrays) -> List:
    """A numba typed list of float64 arrays: one numba type whatever its length, so constant velocity's placeholders and
    every student depth share one compilation of the kernels that take them (a tuple's type would fix its length)."""
    out = List()
    for a in arrays:
        out.append(np.ascontiguousarray(a, float))
    return out


def kernel_args(weights, s) -> tuple:
    """The compiled forward pass's (Ws, bs, s) of GeluStudent.weights64's layers and its head bound s (2N,)."""
    return typed(W for W, _ in weights), typed(b for _, b in weights), np.ascontiguousarray(s, float)


@njit(cache=True)
def gelu(a, derivative):
    """Exact (erf) GELU of a (n,) elementwise, as torch's default, and with `derivative` its derivative (else empty)."""
    h, dh = np.empty_like(a), np.empty(len(a) if derivative else 0)
    for i in range(len(a)):
        cdf = 0.5 * (1.0 + math.erf(a[i] / math.sqrt(2.0)))
        h[i] = a[i] * cdf
        if derivative:  # a rollout's values skip its exp: a sixth of a forward pass
            dh[i] = cdf + a[i] * math.exp(-0.5 * a[i] * a[i]) / math.sqrt(2.0 * math.pi)
    return h, dh


@njit(cache=True)
def head(Ws, bs, x, derivative):
    """GeluStudent's bounded head tanh(W_L h + b_L) (2N,) on one flattened window x (T_obs SLOTS 2,) in m, from its
    float64 layers (kernel_args: P folded into the first W), and with `derivative` each hidden layer's GELU derivative."""
    dhs = []
    for k in range(len(Ws) - 1):
        x, dh = gelu(matvec(Ws[k], x) + bs[k], derivative)
        dhs.append(dh)
    return np.tanh(matvec(Ws[-1], x) + bs[-1]), dhs


@njit(cache=True)
def cv_phi_jac(window):
    """Constant velocity: next xy (SLOTS, 2) of one window (T_obs, SLOTS, 2) in m and its local Jacobian (SLOTS*2,
    T_obs*SLOTS*2)."""
    T_obs, M, _ = window.shape
    J = np.zeros((2 * M, T_obs * 2 * M))
    for r in range(2 * M):
        J[r, (T_obs - 1) * 2 * M + r] = 2.0
        J[r, (T_obs - 2) * 2 * M + r] = -1.0
    return 2.0 * window[-1] - window[-2], J


@njit(cache=True)
def phi_jac(Ws, bs, s, window):
    """GeluStudent in float64 on one window (T_obs, SLOTS, 2) in m: next xy (SLOTS, 2) and its exact local Jacobian
    (SLOTS*2, T_obs*SLOTS*2), the others' rows by one reverse sweep for all 2N outputs."""
    t, dhs = head(Ws, bs, window.copy().reshape(-1), True)
    nxt, J = cv_phi_jac(window)
    G = Ws[-1].copy()  # becomes d head / d hidden, layer by layer back to d head / d window: (2N, width)
    for r in range(len(t)):
        nxt[1 + r // 2, r % 2] += s[r] * t[r]
        G[r] *= s[r] * (1.0 - t[r] * t[r])
    for k in range(len(Ws) - 2, -1, -1):
        G = (G * dhs[k]) @ Ws[k]  # dhs[k] (width,) scales G's columns; BLAS: the hot product, worth its compile time
    for r in range(G.shape[0]):
        for c in range(G.shape[1]):
            J[r + 2, c] += G[r, c]
    return nxt, J


@njit(cache=True)
def phis(Ws, bs, s, windows):
    """GeluStudent in float64: next xy (B, SLOTS, 2) of windows (B, T_obs, SLOTS, 2) in m, a window at a time (so its
    numbers never depend on which others are predicted beside it)."""
    out = 2.0 * windows[:, -1] - windows[:, -2]
    for b in range(len(windows)):
        t, _ = head(Ws, bs, windows[b].copy().reshape(-1), False)
        for r in range(len(t)):
            out[b, 1 + r // 2, r % 2] += s[r] * t[r]
    return out


@njit(cache=True)
def phi_jacs(Ws, bs, s, windows):
    """phi_jac of each window (B, T_obs, SLOTS, 2): next xy (B, SLOTS, 2) and J (B, SLOTS*2, T_obs*SLOTS*2)."""
    B, T_obs, M, _ = windows.shape
    out, J = np.empty((B, M, 2)), np.empty((B, 2 * M, T_obs * 2 * M))
    for b in range(B):
        out[b], J[b] = phi_jac(Ws, bs, s, windows[b])
    return out, J
