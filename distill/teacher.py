"""The teacher: a deterministic Social-GAN-style predictor (GRU encoder per car, social max-pooling, ReLU decoder).

window (B, T_obs, M, 2) xy in metres, ego in slot 0 -> next xy (B, M, 2) in metres. All normalisation is inside:
positions relative to the ego's last position, per-step velocities and accelerations, each divided by a fixed
scale. The decoder predicts each other car's acceleration over the step; the ego slot keeps constant velocity
because the planner overwrites it with its own plan.
"""
import torch
from torch import nn


def relu_mlp(sizes):
    """Linear-ReLU stack with sizes [in, h1, ..., out]; no activation after the last layer."""
    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.ReLU()]
    return nn.Sequential(*layers[:-1])


class GRU(nn.Module):
    """A plain GRU over time (B, T, d_in) -> last hidden state (B, hidden), written out so torch.func can batch it."""

    def __init__(self, d_in, hidden):
        """d_in input features, hidden state size."""
        super().__init__()
        self.hidden = hidden
        self.x_gates = nn.Linear(d_in, 3 * hidden)
        self.h_gates = nn.Linear(hidden, 3 * hidden)

    def forward(self, x):
        """Last hidden state (B, hidden) after reading x (B, T, d_in) from h = 0."""
        h = x.new_zeros(x.shape[0], self.hidden)
        for t in range(x.shape[1]):
            xr, xz, xn = self.x_gates(x[:, t]).chunk(3, dim=-1)
            hr, hz, hn = self.h_gates(h).chunk(3, dim=-1)
            r, z = torch.sigmoid(xr + hr), torch.sigmoid(xz + hz)
            h = (1 - z) * torch.tanh(xn + r * hn) + z * h
        return h


class SocialTeacher(nn.Module):
    """Social GAN's generator made deterministic: encoder GRU, pairwise Pool Net, MLP decoder (scales in m, m/step)."""

    def __init__(self, hidden, pool, decoder, pos_scale, vel_scale, acc_scale):
        """Widths of the GRU state, the Pool Net and the decoder; feature scales in m, m/step, m/step^2."""
        super().__init__()
        self.pos_scale, self.vel_scale, self.acc_scale = pos_scale, vel_scale, acc_scale
        self.encoder = GRU(6, hidden)
        self.slot = nn.Parameter(torch.zeros(5, hidden))  # slot 0 is the ego, 1..4 are ordered front to back
        # Pool Net: each car i looks at every car j through (relative position, relative velocity, j's state).
        self.pool = relu_mlp([4 + hidden, pool, pool])
        self.decoder = relu_mlp([hidden + pool, *decoder, 2])
        nn.init.zeros_(self.decoder[-1].weight)  # start exactly at constant velocity
        nn.init.zeros_(self.decoder[-1].bias)

    def forward(self, window):
        """Next xy (B, M, 2) in metres from window (B, T_obs, M, 2) in metres."""
        h, pooled, vel = self.encode(window)
        return self.decode(window, vel, torch.cat([h, pooled], -1))

    def encode(self, window):
        """Each car's encoding (B, M, hidden), its pooled view of the others (B, M, pool), the window's per-step
        displacements (B, T_obs - 1, M, 2) (m per step)."""
        b, t, m, _ = window.shape
        vel = window[:, 1:] - window[:, :-1]  # m per step
        acc = vel[:, 1:] - vel[:, :-1]
        rel = window - window[:, -1:, :1]  # relative to the ego's last position
        steps = torch.cat([rel[:, 2:] / self.pos_scale, vel[:, 1:] / self.vel_scale, acc / self.acc_scale], -1)
        h = self.encoder(steps.permute(0, 2, 1, 3).reshape(b * m, t - 2, 6)).reshape(b, m, -1) + self.slot[:m]

        last, v_last = rel[:, -1], vel[:, -1]
        d_pos = (last[:, None, :] - last[:, :, None]) / self.pos_scale  # (B, i, j, 2): j seen from i
        d_vel = (v_last[:, None, :] - v_last[:, :, None]) / self.vel_scale
        h_j = h[:, None].expand(b, m, m, h.shape[-1])
        return h, self.pool(torch.cat([d_pos, d_vel, h_j], -1)).max(dim=2).values, vel

    def decode(self, window, vel, features):
        """Next xy (B, M, 2) (m): the decoder's acceleration from each car's features (B, M, d) on its constant velocity."""
        m = window.shape[2]
        acc_next = self.acc_scale * self.decoder(features)
        others = torch.ones(m, 1, dtype=window.dtype, device=window.device)
        others[0] = 0.0
        return window[:, -1] + vel[:, -1] + others * acc_next


class HypothesisTeacher(SocialTeacher):
    """The social teacher under a hypothesis per car, hyp (B, M) with 1: it yields to an encroaching ego, 0: it does not
    (the ego's ignored), fed to the decoder beside its features; a belief head gives p(yields | window) per car."""

    def __init__(self, hidden, pool, decoder, belief, pos_scale, vel_scale, acc_scale):
        """As SocialTeacher's, and the belief head's hidden widths."""
        super().__init__(hidden, pool, decoder, pos_scale, vel_scale, acc_scale)
        self.decoder = relu_mlp([hidden + pool + 1, *decoder, 2])
        nn.init.zeros_(self.decoder[-1].weight)  # start exactly at constant velocity
        nn.init.zeros_(self.decoder[-1].bias)
        self.belief_head = relu_mlp([hidden + pool, *belief, 1])

    def forward(self, window, hyp):
        """Next xy (B, M, 2) in metres from window (B, T_obs, M, 2) in metres under hypotheses hyp (B, M) in {0, 1}."""
        h, pooled, vel = self.encode(window)
        return self.decode(window, vel, torch.cat([h, pooled, hyp[..., None].to(window.dtype)], -1))

    def belief_logit(self, window):
        """log-odds (B, M) that each car yields to the ego, given the window (the ego's meaningless)."""
        h, pooled, _ = self.encode(window)
        return self.belief_head(torch.cat([h, pooled], -1))[..., 0]

    def belief(self, window):
        """p(yields | window) (B, M) per car, the ego's 0."""
        p = torch.sigmoid(self.belief_logit(window))
        return torch.cat([torch.zeros_like(p[:, :1]), p[:, 1:]], 1)
