"""The surrogate network: window (B, T_obs, SLOTS, 2) in metres -> the predictor's local Jacobian (B, SLOTS*2, T_obs*SLOTS*2).

Structure it exploits: a predictor that moves with the traffic (phi(window + c) = phi(window) + c along the road)
has a Jacobian that depends on relative positions only, so the network reads the window relative to the ego's last
position, in velocities and accelerations (plus, optionally, absolute coordinates such as y, if lanes matter). It predicts the
standardised deviation from the training mean Jacobian, so the large constant-velocity part is exact by construction
and its capacity goes to the interaction terms. It reads its features clipped to the box its training data spanned:
outside it an MLP extrapolates without bound, and a chain of T_p such Jacobians multiplies the error (a car changing
lanes in `three_lane`, never seen in the dense world, gave reactions of 10^6 m/m and froze the planner).
"""
import numpy as np
import torch
from torch import nn

AXES = {"x": 0, "y": 1}


class JacobianNet(nn.Module):
    """MLP on relative window features -> J = mean_J + std_J * net(features); lengths in m, J in m/m."""

    def __init__(self, T_obs, M, hidden, depth, absolute):
        """Window of T_obs steps of M slots; `depth` SiLU layers of `hidden` units; absolute: "", "y" or "xy" of the ego."""
        super().__init__()
        self.T_obs, self.M, self.absolute = T_obs, M, [AXES[a] for a in absolute]
        n_in, n_out = (1 + (T_obs - 1) + (T_obs - 2)) * M * 2 + len(self.absolute), M * 2 * T_obs * M * 2
        layers, width = [], n_in
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.SiLU()]
            width = hidden
        self.net = nn.Sequential(*layers, nn.Linear(width, n_out))
        for name, size, fill in (("x_mean", n_in, 0.0), ("x_std", n_in, 1.0), ("x_lo", n_in, -torch.inf),
                                 ("x_hi", n_in, torch.inf), ("J_mean", n_out, 0.0), ("J_std", n_out, 1.0)):
            self.register_buffer(name, torch.full((size,), fill))

    def features(self, window):
        """(B, n_in): kinematic coordinates of the window, the basis the predictors themselves read.

        Positions relative to the ego's last xy (last step only), every per-step velocity and acceleration (m per step,
        per step^2), then the chosen absolute coordinates of the ego's last xy. Velocities and accelerations are small
        differences of large positions; handing them over directly spares the network learning to subtract.
        """
        anchor = window[:, -1:, :1]
        vel = window[:, 1:] - window[:, :-1]
        acc = vel[:, 1:] - vel[:, :-1]
        parts = [(window[:, -1:] - anchor).flatten(1), vel.flatten(1), acc.flatten(1), anchor.flatten(1)[:, self.absolute]]
        return torch.cat(parts, dim=1)

    def standardised(self, window):
        """Network output: (J - J_mean) / J_std, flattened (B, SLOTS*2*T_obs*SLOTS*2), of the features clipped to the
        training box [x_lo, x_hi]."""
        x = torch.minimum(torch.maximum(self.features(window), self.x_lo), self.x_hi)
        return self.net((x - self.x_mean) / self.x_std)

    def outside(self, window):
        """(B,) bool: windows with a feature outside the training box, where the network answers for the box's edge."""
        x = self.features(window)
        return ((x < self.x_lo) | (x > self.x_hi)).any(dim=1)

    def forward(self, window):
        """J (B, SLOTS*2, T_obs*SLOTS*2), m/m."""
        flat = self.J_mean + self.J_std * self.standardised(window)
        return flat.view(-1, self.M * 2, self.T_obs * self.M * 2)

    def fit_normalisation(self, windows, J, floor=1e-3):
        """Set the feature statistics and box and the target statistics from training windows (B, T_obs, SLOTS, 2) and
        Jacobians (B, SLOTS*2, T_obs*SLOTS*2)."""
        x = self.features(torch.as_tensor(np.asarray(windows), dtype=torch.float32))
        J = torch.as_tensor(np.asarray(J).reshape(len(J), -1), dtype=torch.float32)
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(floor))
        self.x_lo.copy_(x.min(0).values)
        self.x_hi.copy_(x.max(0).values)
        self.J_mean.copy_(J.mean(0))
        self.J_std.copy_(J.std(0).clamp_min(floor))


class Fused(nn.Module):
    """window -> (J from the surrogate, next xy from the source predictor): one ONNX call gives the planner both."""

    def __init__(self, surrogate: JacobianNet, source: nn.Module):
        super().__init__()
        self.surrogate, self.source = surrogate, source

    def forward(self, window):
        """(J (B, SLOTS*2, T_obs*SLOTS*2) m/m, next (B, SLOTS, 2) m)."""
        return self.surrogate(window), self.source(window)
