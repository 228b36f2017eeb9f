"""A small smooth interactive predictor for development and tests: constant velocity, but a car yields to an intruding ego.

Car j keeps its last displacement, except that its longitudinal displacement shrinks by up to `slowdown` per step
(about 2.5 m/s^2 at 5 m/s for 0.1) by the weight w_j = L(|y_ego - y_j|) H(x_ego - x_j) in [0, 1]: L is a sigmoid that
switches on once the ego's last position is within `d_react` m laterally of car j, H one that switches on when the
ego is ahead of car j, within `view` m. The ego's own slot is constant velocity (the planner overwrites it).
"""
import numpy as np


def _namespace(a):
    """numpy for arrays, torch for tensors: one formula serves `phi` and the autodiff `module`."""
    if isinstance(a, np.ndarray):
        return np
    import torch

    return torch


def _sigmoid(xp, u):
    """Logistic function of u."""
    return 1.0 / (1.0 + xp.exp(-u))


class Analytic:
    """phi(window) -> next xy (metres); smooth (C-infinity) and interactive, with exact analytic local Jacobians."""

    name = "analytic"

    def __init__(self, d_react, s_lat, s_ahead, view, s_view, slowdown, c=0.1):
        self.d_react, self.s_lat, self.s_ahead = d_react, s_lat, s_ahead
        self.view, self.s_view, self.slowdown, self.c = view, s_view, slowdown, c

    def _weight(self, xp, dx, dy):
        """Yield weight w (and the factors L, H, the smoothed lateral distance d_lat) for ego-minus-car offsets dx, dy (m)."""
        d_lat = xp.sqrt(dy**2 + self.c**2)  # smooth |dy| (m)
        L = _sigmoid(xp, (self.d_react - d_lat) / self.s_lat)
        Ha, Hv = _sigmoid(xp, dx / self.s_ahead), _sigmoid(xp, (self.view - dx) / self.s_view)
        return L * Ha * Hv, L, Ha, Hv, d_lat

    def phi(self, window):
        """Next xy (B, SLOTS, 2) from window (B, T_obs, SLOTS, 2), metres; numpy or torch."""
        xp = _namespace(window)
        last, prev = window[:, -1], window[:, -2]
        disp = last - prev
        ego = last[:, :1]
        w = self._weight(xp, ego[..., 0] - last[..., 0], ego[..., 1] - last[..., 1])[0]
        keep = 1.0 - self.slowdown * w
        keep = xp.concatenate([xp.ones_like(keep[:, :1]), keep[:, 1:]], 1)  # the ego slot is plain constant velocity
        return xp.stack([last[..., 0] + disp[..., 0] * keep, last[..., 1] + disp[..., 1]], -1)

    def phi_jac(self, window):
        """Next xy (B, SLOTS, 2) and the exact local Jacobian d next.flatten() / d window.flatten() (B, SLOTS*2, T_obs*SLOTS*2)."""
        window = np.asarray(window, dtype=float)
        b, t_obs, m, _ = window.shape
        last, prev = window[:, -1], window[:, -2]
        disp = last - prev
        dx, dy = last[:, :1, 0] - last[..., 0], last[:, :1, 1] - last[..., 1]
        w, L, Ha, Hv, d_lat = self._weight(np, dx, dy)
        w[:, 0] = 0.0
        dw_ddy = -L * (1 - L) / self.s_lat * dy / d_lat * Ha * Hv
        dw_ddx = L * (Ha * (1 - Ha) / self.s_ahead * Hv - Ha * Hv * (1 - Hv) / self.s_view)
        dw_ddy[:, 0] = dw_ddx[:, 0] = 0.0
        keep = 1.0 - self.slowdown * w
        J = np.zeros((b, m, 2, t_obs, m, 2))
        j = np.arange(m)
        J[:, j, 0, -1, j, 0] = 1.0 + keep
        J[:, j, 0, -2, j, 0] = -keep
        J[:, j, 1, -1, j, 1] = 2.0
        J[:, j, 1, -2, j, 1] = -1.0
        g = -self.slowdown * disp[..., 0]  # d next_x / d w
        J[:, j, 0, -1, j, 0] -= g * dw_ddx  # dx = x_ego - x_j
        J[:, j, 0, -1, j, 1] -= g * dw_ddy
        J[:, :, 0, -1, 0, 0] += g * dw_ddx
        J[:, :, 0, -1, 0, 1] += g * dw_ddy
        return self.phi(window), J.reshape(b, m * 2, t_obs * m * 2)

    @property
    def module(self):
        """The same phi as a torch module (window tensor -> next tensor, metres), for autodiff."""
        import torch

        phi = self.phi

        class AnalyticModule(torch.nn.Module):
            def forward(self, window):
                return phi(window)

        return AnalyticModule()
