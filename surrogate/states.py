"""Planning states like the ones the planner visits: a history with the ego moved, and an ego plan over T_p steps.

The planner's Z-iterates put the ego where no dataset window has it: shifted along and across the road, faster or
slower, halfway through a lane change, or zig-zagging (an early, off-distribution iterate). The surrogate must be
accurate there, so its training data and its held-out test are drawn from this family.
"""
import numpy as np


def smoothstep(u):
    """0 -> 1 on u in [0, 1] with zero slope at both ends (a lane-change profile)."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


class PlanSampler:
    """Random planning states around dataset histories; lengths in m, speeds as factors of the ego's last speed."""

    def __init__(self, T_p, shift_x, shift_y, p_shift, p_mid_lane_change, lane_width, plan_y, speed_factor, jitter,
                 p_jitter):
        """Horizon T_p (steps); ego shifts (m, std) with probability p_shift; mid-lane-change histories with probability
        p_mid_lane_change; plans reach up to plan_y (m) across at speed_factor [low, high]; zig-zag jitter (m, std)."""
        self.T_p, self.shift_x, self.shift_y, self.p_shift = T_p, shift_x, shift_y, p_shift
        self.p_mid_lane_change, self.lane_width, self.plan_y = p_mid_lane_change, lane_width, plan_y
        self.speed_factor, self.jitter, self.p_jitter = speed_factor, jitter, p_jitter

    def sample(self, history, rng):
        """(history' (B, T_obs, SLOTS, 2) with the ego's track moved, ego_future (B, T_p, 2)) in metres."""
        history = np.array(history, dtype=np.float64)
        B, t_obs = history.shape[:2]
        ego = history[:, :, 0]  # (B, T_obs, 2), a view: edits move the ego in `history`
        shifted = rng.random(B) < self.p_shift
        ego += (shifted[:, None] * rng.normal(0.0, [self.shift_x, self.shift_y], (B, 2)))[:, None]
        mid = rng.random(B) < self.p_mid_lane_change  # the history ends partway through a lateral move
        reach = rng.choice([-1.0, 1.0], B) * self.lane_width * rng.uniform(0.2, 0.8, B)
        ego[..., 1] += (mid * reach)[:, None] * smoothstep(np.linspace(0.0, 1.0, t_obs))[None]

        step = ego[:, -1] - ego[:, -2]  # m per step
        speed = rng.uniform(*self.speed_factor, B)
        ramp = np.arange(1, self.T_p + 1) / self.T_p
        along = np.cumsum(1.0 + (speed[:, None] - 1.0) * ramp[None], axis=1)  # steps travelled, speed ramping
        lateral = rng.uniform(-self.plan_y, self.plan_y, B)[:, None] * smoothstep(ramp * rng.uniform(0.8, 2.0, B)[:, None])
        future = ego[:, -1, None] + along[..., None] * np.stack([step[:, 0], np.zeros(B)], -1)[:, None]
        future[..., 1] += step[:, 1, None] * np.arange(1, self.T_p + 1) * (1.0 - mid[:, None]) + lateral
        zigzag = rng.random(B) < self.p_jitter
        future += zigzag[:, None, None] * rng.normal(0.0, self.jitter, future.shape)
        return history, future
