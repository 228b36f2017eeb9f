"""The planner as a gymnasium policy for highway-env's dense merge (data.highway, `admm-nnmpc/DenseMerge-v0`).

    env = gymnasium.make("data.highway:admm-nnmpc/DenseMerge-v0")  # the module registers the id
    policy = MergePolicy(["gradients=student", "method=admm"])
    obs, info = env.reset(seed=2000000)
    policy.reset()
    while True:
        obs, reward, terminated, truncated, info = env.step(policy(obs))
        if terminated or truncated:
            break
    info["courteous"]

It sees only the observations (absolute states with ids) and keeps each car's own past, as data.perception does for our
world: the n_slots cars nearest the ego, in id order, each with its history (constant velocity before it was first
seen). The frame and action mapping is data.highway's (to_ours, to_action), nowhere else.
"""
import numpy as np

from core import validate
from core.jobs import UserError, build, check_overrides
from data.highway import ENV_ID, DenseMergeEnv, check_action, to_action, to_ours
from data.perception import slot_ids
from data.world import backfill
from planner.mpc import Observation
from planner.setup import planner_config, setup

JUMP_M = 2.0  # m: how far a car may be from where its speeds put it one step later (a new episode moves them tens of m)


class MergePolicy:
    """reset(), then policy(observation) -> the env's action; `overrides` are the `planner` command's (scenario=highway
    unless given), `action` the env's action config (its ranges; the env's default if None)."""

    def __init__(self, overrides=(), action=None):
        if not isinstance(overrides, (list, tuple)) or not all(isinstance(o, str) for o in overrides):
            raise UserError(f"MergePolicy: overrides={overrides!r}: a list of `planner` overrides, such as ['gradients=cv']")
        overrides = list(overrides)
        scenario = next((o.split("=", 1)[1] for o in overrides if o.startswith("scenario=")), "highway")
        rest = [o for o in overrides if not o.startswith("scenario=")]
        check_overrides("planner", [f"scenario={scenario}", *rest])  # one line for an unknown key or option, as `planner`
        cfg = planner_config(scenario, rest)
        validate.check(cfg, "planner")  # the checks the `planner` command makes
        methods = list(cfg.method)
        if len(methods) != 1:
            raise UserError(f"method={'+'.join(methods)}: a policy drives one method; choose method=admm or method=nnmpc")
        self.scenario, self.source, self.settings = setup(cfg)
        if self.source.needs_world:
            raise UserError("gradients=oracle reads the running world; a gymnasium policy has only observations")
        self.step = build(cfg.method[methods[0]])
        self.T_obs, self.n_slots, self.dt = cfg.T_obs, cfg.n_slots, self.scenario.params.dt
        default = DenseMergeEnv.default_config()["action"]
        action = default if action is None else {**default, **action} if isinstance(action, dict) else action
        check_action(action)  # the ranges given, the env's default for any left out
        self.ranges = action["acceleration_range"], action["steering_range"]
        self.pasts = self.seen = None
        self.last = None  # the last planning step's result (fallback reason, cost, iterations)

    def reset(self):
        """Forget the last episode: histories, the last control and the warm start."""
        self.pasts, self.seen, self.u_prev, self.warm = {}, {}, np.zeros(2), None

    def observe(self, observation) -> Observation:
        """The planner's Observation from an env observation (rows [present, id, x, y, heading, speed])."""
        if self.pasts is None:
            raise UserError("MergePolicy: call reset() at the start of every episode, before the first observation")
        try:
            rows = np.asarray(observation, float)
        except (TypeError, ValueError):
            rows = np.zeros(0)
        if rows.ndim != 2 or rows.shape[1] != 6 or not np.isfinite(rows).all():
            raise UserError(f"MergePolicy: an observation is rows [present, id, x, y, heading, speed] of finite numbers "
                            f"({ENV_ID}'s), not {np.shape(observation)}")
        rows = rows[rows[:, 0] > 0.5]
        if (rows[:, 1] != np.round(rows[:, 1])).any() or (rows[:, 1] < 0).any():
            bad = sorted(float(i) for i in rows[:, 1] if i != round(i) or i < 0)
            raise UserError(f"MergePolicy: car ids are whole numbers >= 0, not {bad}")
        ids, z = rows[:, 1].astype(int), to_ours(rows[:, 2:6])
        if len(ids) == 0 or ids[0] != 0:
            raise UserError("MergePolicy: the observation holds no ego row (id 0 first)")
        if len(set(ids)) < len(ids):
            twice = sorted({int(i) for i in ids if list(ids).count(i) > 1})
            raise UserError(f"MergePolicy: car ids {twice} appear twice in one observation")
        self.check_continuity(ids, z)
        for i, zi in zip(ids, z):
            past = self.pasts.get(i)
            self.pasts[i] = (list(backfill(zi[None], self.T_obs, self.dt)[:, 0]) if past is None else past + [zi[:2]])[-self.T_obs:]
        if len(ids) - 1 < self.n_slots:  # fewer cars in view than slots: pad with cars far behind, never reached
            far = np.array([[z[0, 0] - 200.0 - 10.0 * k, z[0, 1], 0.0, 0.0] for k in range(self.n_slots + 1 - len(ids))])
            z = np.vstack([z, far])
            pasts = [np.array(self.pasts[i]) for i in ids] + [np.repeat(f[None, :2], self.T_obs, 0) for f in far]
        else:
            pasts = [np.array(self.pasts[i]) for i in ids]
        slots = slot_ids(z, self.n_slots)
        history = np.stack([pasts[k] for k in slots], axis=1)
        return Observation(z[0].copy(), self.u_prev.copy(), history)

    def check_continuity(self, ids, z):
        """One UserError where the ego, or most of the other cars seen last time, moved further since the last observation
        than their speeds allow in one step of dt: a new episode without reset() (or a step not shown to the policy) would
        mix the histories of two worlds."""
        def jumped(i):  # distance against the mean speed's, with room for a step's hardest braking and yaw
            (xy0, v0), xy1, v1 = self.seen[i], z[k[i], :2], z[k[i], 3]
            return abs(np.linalg.norm(xy1 - xy0) - 0.5 * (v0 + v1) * self.dt) > JUMP_M
        k = {i: n for n, i in enumerate(ids)}
        both = [i for i in ids if i in self.seen]
        others = [i for i in both if i != 0]
        if (0 in both and jumped(0)) or (others and sum(map(jumped, others)) > len(others) / 2):
            raise UserError("MergePolicy: the cars moved further than their speeds allow since the last observation: "
                            "call reset() at the start of every episode, and the policy on every step")
        self.seen = {i: (z[n, :2].copy(), z[n, 3]) for n, i in enumerate(ids)}

    def __call__(self, observation) -> np.ndarray:
        """The env's action [acceleration, steering] in [-1, 1] for this observation."""
        self.last = self.step(self.settings, self.observe(observation), self.source, self.warm)
        self.u_prev, self.warm = np.nan_to_num(self.last.u), self.last.plan
        return to_action(self.u_prev, *self.ranges)
