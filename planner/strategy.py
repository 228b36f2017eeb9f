"""Strategies: which plans a step solves from and which solved plan it applies. A strategy has two methods,
`candidates(s, obs, warm, source) -> [Start]` and `choose(s, obs, plans) -> (Start, StepResult)` over the plans that passed the
safeguard; it is the `mpc.strategy` node of the `planner` config.

- `Paper`: Algorithm 1 as published, one solve from the shifted previous plan.
- `Rules` (mpc=courteous, the engineered baseline): several solves from plans that hold the lane, two hand-written
  behaviour rules (a nominal IDM follower that judges the gap a plan leaves, and `KeepAhead`, which reads a yielding
  driver off the history) and a ranked choice.
- `Interactive` (mpc=interactive): no behaviour rule; generic candidate plans judged by the predictor's rollout alone.
"""
from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from core.jobs import UserError
from core.rollout import b_i, braking
from core.validate import Int, ListOf, OneOf, Real, check_fields, rule
from data import bicycle
from data.drivers import IDMDriver
from planner import admm, jit_chase, jit_interactive, jit_rollout
from planner.mpc import Observation, Settings, costs, lane_plans, planned, simulate, warm_start

NONNEG = Real(0)
STOP_MARGIN = 2.0  # m: a chasing candidate keeps able to stop this far before its lane's end, braking as hard as a_box allows
FAR = 1e4  # m: moved this far along the road, a car outside the target lane leaves the room beside a candidate free (Interactive.room)
K_PSI = 4.0  # 1/s: a candidate's heading loop (drive), faster than any lateral gain k_y it serves: at the world's 2.0 a brisk lean overshot its depth into the safety shape of the car beside


class Start(NamedTuple):
    """One solve of a step: its name, where ADMM starts, the settings it solves with (the scenario's, or with y_ref and
    v_ref moved; None: no solve, the plan is offered as it is to the safeguard's check) and its rank in the choice
    (lower first)."""

    name: str
    plan: admm.ADMMState
    aim: Settings | None
    rank: float


@dataclass(frozen=True)
class Paper:
    """Algorithm 1 as published: one ADMM solve from the shifted previous plan (cold: zero inputs), applied as it is."""

    def candidates(self, s: Settings, obs: Observation, warm, source) -> list[Start]:
        """The shifted previous plan."""
        return [Start("shifted", warm_start(s, obs, warm), s, 0.0)]

    def choose(self, s: Settings, obs: Observation, plans):
        """The one plan."""
        return plans[0]


def target_lane(s: Settings, windows):
    """(x (..., SLOTS) m, v (..., SLOTS) m/s, in the target lane (..., SLOTS) bool, the ego's slot False) from the last
    two steps of windows (..., T, SLOTS, 2): many predicted windows at once."""
    x, y = windows[..., -1, :, 0], windows[..., -1, :, 1]
    v = (x - windows[..., -2, :, 0]) / s.params.dt
    there = s.road.lane_of(y) == s.road.lane_of(s.y_ref)
    there[..., 0] = False
    return x, v, there


def seen_target_lane(s: Settings, history):
    """(x (SLOTS,) m, v (SLOTS,) m/s, the slots of the other cars in the target lane) from the last two observed steps
    of the history (T_obs, SLOTS, 2)."""
    x, v, there = target_lane(s, history)
    return x, v, np.flatnonzero(there)


@dataclass(frozen=True)
class KeepAhead:
    """When the nearest target-lane car behind the ego (within `near` m) is seen slowing for it, the lean starts aim at
    that car's speed plus dv instead of their own v, so a driver who yields to the nudge is not overtaken by it (SI)."""

    near: float = rule(NONNEG)  # m: how far behind the ego's centre that car's centre may be
    dv: float = rule(NONNEG)  # m/s: kept above its speed
    slowing: float = rule(NONNEG)  # m/s^2: it counts as slowing once it decelerates harder than this over the last observed steps
    slower: float = rule(NONNEG)  # m/s: ... or drives this much slower than the target-lane car ahead of the ego

    def __post_init__(self):
        check_fields(self, "mpc.strategy.keep_ahead")

    def speed(self, s: Settings, history):
        """The speed (m/s) of the nearest target-lane car behind the ego, within `near`, when the observed history
        (T_obs, SLOTS, 2) shows it slowing for the ego; None when there is none, or it is not slowing."""
        if len(history) < 3:  # no acceleration to read
            return None
        x, v, target = seen_target_lane(s, history)
        behind = target[(x[target] <= x[0]) & (x[target] >= x[0] - self.near)]
        if len(behind) == 0:
            return None
        b = behind[np.argmax(x[behind])]
        decel = -(history[-1, b, 0] - 2 * history[-2, b, 0] + history[-3, b, 0]) / s.params.dt**2
        ahead = target[x[target] > x[0]]
        lag = v[ahead[np.argmin(x[ahead])]] - v[b] if len(ahead) else 0.0
        return float(v[b]) if decel > self.slowing or lag > self.slower else None


@dataclass(frozen=True)
class Rules:
    """mpc=courteous's strategy: besides the shifted plan, ADMM solves from holding the lane and aims off it (`starts`,
    each [offset m, a m/s^2, v m/s or None: v_ref]); a lean beside a car seen yielding keeps ahead of it (`keep_ahead`);
    the plan applied has the least braking above b_courtesy, predicted or the nominal `follower`'s, then merges by the
    lowest J, else waits as the first start says."""

    starts: tuple
    progress: float = rule(NONNEG)  # m: a plan that ends this much nearer y_ref than the ego is now, or in the target lane, merges
    follower: dict | None  # a nominal IDM driver's parameters that differ from IDMDriver's defaults; None: none
    keep_ahead: KeepAhead | None  # None: the lean starts keep their own v

    def __post_init__(self):
        check_fields(self, "mpc.strategy")
        for start in self.starts:
            ok = isinstance(start, (list, tuple)) and len(start) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in start[:2])
            if not ok or not (start[2] is None or (isinstance(start[2], (int, float)) and start[2] >= 0)):
                raise UserError(f"mpc.strategy.starts: {start} must be [offset m, a m/s^2, v m/s >= 0 or null]")
        known = set(IDMDriver.__dataclass_fields__)
        for key, value in (self.follower or {}).items():
            if key not in known:
                raise UserError(f"mpc.strategy.follower.{key}: IDMDriver has no such parameter (it has {', '.join(sorted(known))})")
            if not isinstance(value, (int, float)) or not np.isfinite(value) or value < 0:
                raise UserError(f"mpc.strategy.follower.{key}={value}: must be a finite number >= 0")

    @cached_property
    def driver(self) -> IDMDriver | None:
        """The nominal follower, IDMDriver with `follower`'s parameters over its defaults; None without one."""
        return None if self.follower is None else IDMDriver(**self.follower)

    def candidates(self, s: Settings, obs: Observation, warm, source) -> list[Start]:
        """The shifted plan, ranked after the starts that lean in (offset > 0) and before those that wait in lane (when a
        lean's plan fails or imposes braking, the shifted plan, leaning already, goes on asking the driver behind instead
        of dropping back to the lane centre), then one Start per `starts` entry: ADMM aims at y_ref = the current lane's
        centre moved `offset` towards the scenario's y_ref (0: wait in lane; 1.9: lean in, the nudge) and at v_ref = v
        (None: the scenario's), from holding the lane at a (mpc.lane_plans); with keep_ahead a lean beside a car seen
        yielding aims at that car's speed plus dv. The target lane's pull would draw every start into one basin; these
        solves stay in theirs (choose)."""
        out = [Start("shifted", warm_start(s, obs, warm), s, sum(float(o) > 0 for o, _, _ in self.starts) + 0.5)]
        lane_y = s.road.centre(s.road.lane_of(obs.z0[1]))
        v_yield = self.keep_ahead.speed(s, obs.history) if self.keep_ahead is not None else None
        plans = zip(*lane_plans(s, obs.z0, [a for _, a, _ in self.starts]))  # held lanes, rolled out together
        for rank, ((offset, _, v), (Delta, alpha, Z)) in enumerate(zip(self.starts, plans), 1):
            y, v = lane_y + float(offset) * np.sign(s.y_ref - lane_y), s.v_ref if v is None else float(v)
            if offset > 0 and v_yield is not None:
                v = float(np.clip(v_yield + self.keep_ahead.dv, *s.v_box))
            out.append(Start(f"y {y:+.1f} m, v {v:.1f} m/s", planned(s, obs.z0, Delta, alpha, Z),
                             replace(s, y_ref=y, v_ref=v), rank))
        return out

    def follower_braking(self, s: Settings, obs: Observation, Z, values) -> float:
        """The hardest braking (m/s^2, >= 0) that the nominal follower would need behind the ego's plan Z (4T_p,), for
        each other car behind the ego in the plan's lane at a step: there by the predictor's values (T_p, SLOTS, 2), or
        last seen there (the world has a car changing lanes follow the leaders of both); 0 without a follower. Constant
        velocity predicts no braking; this judges the gap a plan leaves, whoever predicts the positions."""
        if self.driver is None:
            return 0.0
        ego = Z.reshape(-1, 4)
        x = np.concatenate([obs.history[-1:, 1:, 0], values[:, 1:, 0]])  # (T_p + 1, N), the last observed step first
        v = np.diff(x, axis=0) / s.params.dt  # (T_p, N): along the road, as IDM follows
        lane = s.road.lane_of(ego[:, 1])[:, None]
        there = (s.road.lane_of(values[:, 1:, 1]) == lane) | (s.road.lane_of(obs.history[-1, 1:, 1]) == lane)
        behind = there & (values[:, 1:, 0] < ego[:, :1])
        a = [self.driver.acceleration(v[k, i], ego[k, 0] - values[k, i + 1, 0] - s.road.car_length, ego[k, 3])
             for k, i in zip(*np.nonzero(behind))]
        return float(max(0.0, -min(a, default=0.0)))

    def choose(self, s: Settings, obs: Observation, plans):
        """Among solved (Start, StepResult), each given its follower's braking: the least braking above b_courtesy
        (m/s^2), predicted or the follower's (without courtesy rows, b_safe is not the planner's to judge: none), then a
        merge (a plan that ends in the target lane, or `progress` nearer y_ref than the ego) by the lowest cost J;
        without one, the lowest rank, so an ego that cannot merge yet waits as the first start says instead of pressing
        on beside the gap (the scenario's J, which pulls towards y_ref, would choose that), then J."""
        plans = [(st, r._replace(follower_braking=self.follower_braking(s, obs, r.plan.Z, r.values))) for st, r in plans]
        if len(plans) == 1:
            return plans[0]
        y0 = obs.z0[1]
        excess = lambda r: 0.0 if s.b_courtesy is None else max(0.0, r.braking - s.b_courtesy, r.follower_braking - s.b_courtesy)
        merges = lambda r: (s.road.lane_of(r.plan.Z[-3]) == s.road.lane_of(s.y_ref)
                            or abs(s.y_ref - y0) - abs(s.y_ref - r.plan.Z[-3]) >= self.progress)
        return min(plans, key=lambda p: (excess(p[1]), (0, p[1].J) if merges(p[1]) else (1, p[0].rank, p[1].J)))


def paces(s: Settings, history, H: int, tau_x: float, stream_dv=(0.0,)) -> dict:
    """The longitudinal profiles a candidate may follow over H steps, from the last two observed steps of the history
    (T_obs, SLOTS, 2): {name: (v_target (H,) m/s, x_target (H,) m or NaN: speed only)}. Stopped; the ego's own speed;
    the target lane's mean plus each of stream_dv (m/s: below it, the stream passes a leaning ego car by car); and for
    each gap between two consecutive target-lane cars seen, its middle as both cars would move at their observed
    speeds, tracked with time constant tau_x (s): where a merge into that gap would start."""
    x, v, target = seen_target_lane(s, history)
    t = np.arange(1, H + 1) * s.params.dt
    speed = lambda u: (np.full(H, u), np.full(H, np.nan))
    out = {"stop": speed(0.0), "own": speed(v[0])}
    if len(target):
        out.update({f"stream {dv:+.1f} m/s" if dv else "stream": speed(max(0.0, v[target].mean() + dv)) for dv in stream_dv})
    target = target[np.argsort(x[target])]
    for back, front in zip(target[:-1], target[1:]):
        v_gap = 0.5 * (v[back] + v[front])
        middle = 0.5 * (x[back] + x[front]) + v_gap * t
        name = f"gap {x[back] - x[0]:+.0f}..{x[front] - x[0]:+.0f} m"
        out[name] = (np.full(H, v_gap), middle)
    return out


def entering_speed(s: Settings, history) -> float:
    """The speed (m/s) a candidate holds once in the target lane: the observed speed of the nearest target-lane car ahead
    of the ego, else the target lane's mean, else the ego's own, from the last two steps of the history (T_obs, SLOTS, 2)."""
    x, v, target = seen_target_lane(s, history)
    ahead = target[x[target] > x[0]]
    return float(v[ahead[np.argmin(x[ahead])]] if len(ahead) else v[target].mean() if len(target) else v[0])


def drive(s: Settings, z, y_target, a, k_y: float):
    """Controls delta, a (K,) in rad, m/s^2 and next states (K, 4) of K egos in states z (K, 4) that steer to the lateral
    targets y_target (K,) in m with lateral gain k_y (1/s) and heading gain K_PSI, their heading held within psi_box,
    accelerating at a (K,) within a_box, never reversing."""
    p, clip = s.params, lambda u, box: np.minimum(np.maximum(u, box[0]), box[1])  # np.clip's numbers, without its wrapping's microseconds
    v = np.maximum(z[:, 3], 1.0)
    psi_d = clip(np.arctan(k_y * (y_target - z[:, 1]) / v), s.psi_box)
    d = clip((p.l_f + p.l_r) * K_PSI * (psi_d - z[:, 2]) / v, s.delta_box)
    a = np.maximum(clip(a, s.a_box), -z[:, 3] / p.dt)
    return d, a, bicycle.step(z, np.array([d, a]).T, p)  # np.stack took 4 us more


def car(s: Settings, k_y: float) -> tuple:
    """jit_interactive.drive's car: (l_f, l_r m, dt s, psi_box rad, delta_box rad, a_box m/s^2, k_y, K_PSI 1/s), as
    drive reads s and its gains."""
    p = s.params
    return tuple(float(c) for c in (p.l_f, p.l_r, p.dt, *s.psi_box, *s.delta_box, *s.a_box, k_y, K_PSI))


def track(s: Settings, z0, y_target, v_target, tau: float, k_y: float, x_target=None, tau_x: float = 1.0):
    """Controls Delta, alpha (K, H) and states Z (K, 4H) of K candidates that steer to the lateral targets y_target
    (K, H) in m with lateral gain k_y in 1/s (drive) while their speed approaches v_target (K, H) in m/s with time
    constant tau (s); where x_target (K, H) in m is given (not NaN), the speed aimed at also closes the distance to it
    with time constant tau_x (s)."""
    K, H = y_target.shape
    x_target = np.full((K, H), np.nan) if x_target is None else x_target
    speed_only = np.isnan(x_target)  # once: np.nan_to_num each step cost more than the rest of the step's maths
    z = np.repeat(np.asarray(z0, float)[None], K, 0)
    Delta, alpha, Z = [], [], []
    for k in range(H):
        v_aim = np.maximum(0.0, v_target[:, k] + np.where(speed_only[:, k], 0.0, (x_target[:, k] - z[:, 0]) / tau_x))
        d, a, z = drive(s, z, y_target[:, k], (v_aim - z[:, 3]) / tau, k_y)
        Delta.append(d)
        alpha.append(a)
        Z.append(z)
    return np.stack(Delta, 1), np.stack(alpha, 1), np.concatenate(Z, 1)


class Chase:
    """K closed-loop candidates, each chasing one gap of the target lane as the predictor moves its cars: the ego's
    speed closes on the gap's middle (time constants tau, tau_x in s), never so fast that it could not stop STOP_MARGIN
    before the lane's end braking as hard as a_box allows; within `align` m of the middle it leans to lean_y (m) to ask
    for room; once the predicted bumper clearances to both gap cars reach `clearance` (m) it steers into the target
    lane, and there follows the nearest car ahead by IDM. A gap with no seen car ahead (behind) ends at the nearest
    place an unseen car may be (`unseen`). A candidate with a finite `dv` (m/s) accepts a gap instead of chasing one:
    leaning, it holds the speed of the target-lane cars near it plus dv (never below 0: a large negative dv waits at a
    standstill while the stream passes) and steers in once the gap beside it, between the nearest cars ahead and behind
    as predicted, leaves its clearance ahead and either its clearance behind or a car behind predicted to have stopped
    for it (below V_STOPPED). The predictor's rollout calls it once a step (Source.react)."""

    V_STOPPED = 0.5  # m/s: a car behind this slow has stopped for the ego (the ceiling's gap acceptance)
    NEAR = 15.0  # m: the target-lane cars whose mean speed an accepting candidate holds (the ceiling's)

    FOLLOW = IDMDriver(T=0.6, s0=1.5, a_max=2.0, b=3.0)  # the ego's own car-following once in the target lane

    def __init__(self, s: Settings, z0, gaps, lean_y, clearance, lane_y: float, lane_end: float, tau: float,
                 tau_x: float, align: float, unseen, k_y: float, dv=None):
        self.s, self.gaps, self.k_y = s, np.asarray(gaps, int).reshape(-1, 2), k_y
        self.lean_y, self.clearance = np.asarray(lean_y, float), np.asarray(clearance, float)
        self.dv = np.full(len(self.gaps), np.nan) if dv is None else np.asarray(dv, float)
        self.constants = tuple(float(c) for c in (  # jit_chase.chase_step's scalars after k, in its order
            *unseen, lane_y, s.y_ref, lane_end - STOP_MARGIN, -2.0 * s.a_box[0], tau, tau_x, align, s.params.dt,
            s.road.car_length, s.road.lane_width, self.NEAR, self.V_STOPPED))
        self.z = np.repeat(np.asarray(z0, float)[None], len(self.gaps), 0)
        self.Delta, self.alpha, self.Z = [], [], []

    def __call__(self, window, k):
        """The egos' xy (K, 2) one step on from the last step of the predicted windows (K, T_obs, SLOTS, 2)."""
        s, z = self.s, self.z
        x, v, there = target_lane(s, window)  # (K, SLOTS)
        a, y_t, follow, gap, v_lead, cap = jit_chase.chase_step(x, v, there, z, self.gaps, self.dv, self.lean_y,
                                                                self.clearance, k, *self.constants)
        for b in np.flatnonzero(follow):  # few at a step: IDM by the world's own driver model
            a[b] = min(self.FOLLOW.acceleration(z[b, 3]) if np.isnan(gap[b]) else
                       self.FOLLOW.acceleration(z[b, 3], gap[b], v_lead[b]), cap[b])
        d, a, self.z = drive(s, z, y_t, a, self.k_y)
        self.Delta.append(d)
        self.alpha.append(a)
        self.Z.append(self.z)
        return self.z[:, :2]

    def compiled(self, params, history, T: int):
        """Delta, alpha (K, T), Z (K, 4T) and the predicted xy (K, T, SLOTS, 2) of these candidates driven T steps
        against a predictor the compiled core runs (params: jit_rollout.compiled_params) from the observed history
        (T_obs, SLOTS, 2), in one compiled call (jit_interactive.chase): Source.react(history, self, T, K)'s, to rounding."""
        s = self.s
        lane = (s.params.dt, s.road.lane_width, float(s.road.lanes), float(s.road.lane_of(s.y_ref)))
        return jit_interactive.chase(*params, np.asarray(history, float), self.z, self.gaps, self.dv, self.lean_y,
                                     self.clearance, T, self.constants, lane, car(s, self.k_y), self.FOLLOW.following)


def unseen(s: Settings, history) -> tuple:
    """(x ahead m, x behind m, v m/s): the nearest places along the road where a target-lane car the predictor does not
    see may be at the last step of the history (T_obs, SLOTS, 2), and the speed it is taken to drive at (the target
    lane's mean, else the ego's). Perception keeps the nearest cars (data.perception), so an unseen car is no nearer the
    ego than the farthest seen one: in dense traffic, a gap beyond the seen cars is not open but unknown."""
    x, v, target = seen_target_lane(s, history)
    xy = history[-1]
    r = np.hypot(*(xy[1:] - xy[0]).T).max(initial=0.0)
    along = np.sqrt(max(r**2 - (s.y_ref - xy[0, 1]) ** 2, 0.0))
    return x[0] + along, x[0] - along, float(v[target].mean() if len(target) else v[0])


def gaps(s: Settings, history) -> list:
    """The gaps of the target lane seen in the last step of the history (T_obs, SLOTS, 2), back to front: (name, front
    slot, back slot), slot 0 where no car is seen ahead (behind): up to the nearest unseen car (`unseen`)."""
    x, _, target = seen_target_lane(s, history)
    cars = [0, *target[np.argsort(x[target])], 0]
    where = lambda i: f"{x[i] - x[0]:+.0f}" if i else "unseen"
    return [(f"{where(back)}..{where(front)} m", front, back) for back, front in zip(cars[:-1], cars[1:])]


def compiled(source) -> bool:
    """Whether the candidate search runs in compiled calls for this source: its predictor's rollout is written as numba
    kernels (cv, the student), whichever source gives the Z-step its Jacobians."""
    return jit_rollout.values_params(source.predictor) is not None


class Judged(NamedTuple):
    """What the predictor's rollout over a candidate's horizon says of it: min b_i (m^2), the hardest braking it
    imposes on another car (m/s^2), the first step it has merged (within merge_tol of y_ref; Interactive.never: none), its
    cost J over T_p, how far (m) it runs out of road: past the point from which, not yet merged, it could still
    stop before its lane's end braking as hard as a_box allows (0: never), and the most room (m^2) it is predicted to
    find beside it in the target lane (Interactive.room; 0 where the order does not read it)."""

    b_min: float
    braking: float
    merge: int
    J: float
    overrun: float = 0.0
    room: float = 0.0


@dataclass(frozen=True)
class Interactive:
    """mpc=interactive: no behaviour rule. Two families of candidate plans, each rolled out by the predictor over
    `horizon` steps (beyond T_p, so a plan that positions for a later merge has a value). Open loop: wait in lane, lean
    towards the target lane by `lean`, or lean and then steer into it after each of `merge_steps`, each with a
    longitudinal profile (`paces`: stopped, its own speed, the stream's, or closing on the middle of a gap between two
    target-lane cars). Closed loop (`Chase`): for each gap seen in the target lane, each depth of `chase_lean` and each
    `clearance`, a policy that answers the predictor's moves step by step (the predictor's own recursion drives it:
    Source.react). A candidate counts when the predicted others stay outside the safety shape and nobody is predicted to
    brake harder than b_courtesy; among those the earliest merge, then (`wait_by`) the most room predicted beside a
    candidate that merges within no horizon, then the lowest J. The best `refine` are refined by ADMM (Algorithm 1)
    towards their own aim and also offered as they are; the plan applied is the first by that order whose step-horizon
    braking stays within b_courtesy."""

    lean: float = rule(Real(0))  # m: towards the target lane from the current lane's centre
    merge_steps: tuple = rule(ListOf(Int(0), at_least=1))  # steps (of dt) after which a leaning candidate steers into the target lane
    horizon: int = rule(Int(1))  # steps (of dt) over which the predictor judges an open-loop candidate; at least T_p
    chase_horizon: int = rule(Int(1))  # steps (of dt) over which it judges a closed-loop one; at least T_p
    tau: float = rule(Real(0, lo_open=True))  # s: time constant of a candidate's speed approaching its target
    tau_x: float = rule(Real(0, lo_open=True))  # s: time constant of a gap-targeting candidate closing on the gap's middle
    k_y: float = rule(Real(0, lo_open=True))  # 1/s: a candidate's lateral gain (drive): how briskly it leans and crosses, within psi_box
    stream_dv: tuple = rule(ListOf(Real(), at_least=1))  # m/s: the speeds relative to the stream's mean a candidate may hold
    chase_lean: tuple = rule(ListOf(Real(0)))  # m: how far a gap-chasing candidate leans to ask for room; []: no such candidates
    clearance: tuple = rule(ListOf(Real(0), at_least=1))  # m: predicted bumper clearance to both gap cars at which a chasing candidate enters
    accept_dv: tuple = rule(ListOf(Real()))  # m/s: for each, closed-loop candidates that lean at the nearby stream's speed plus it and accept the gap beside them; []: none
    align: float = rule(Real(0))  # m: a chasing candidate leans only this close to its gap's middle
    lane_end: float = rule(Real())  # m: where the ego's lane ends (the scenario's x_ref): a chasing candidate can always stop before it
    refine: int = rule(Int(1))  # how many of the best candidates ADMM refines
    merge_tol: float = rule(Real(0, lo_open=True))  # m: a candidate has merged once its centre is this close to y_ref (the scenario's)
    wait_by: str = rule(OneOf(("room", "J")))  # how candidates that merge within no horizon are ordered before J: by the most room predicted beside them (room), or not (J)
    trust: int | None = rule(Int(1, nullable=True))  # steps of a learned (`fitted`) predictor's rollout the verdicts read; beyond, every other car goes on at its last predicted velocity (None: all)

    def __post_init__(self):
        check_fields(self, "mpc.strategy")

    def never(self, s: Settings) -> int:
        """The merge step of a verdict whose candidate does not merge: one past both families' horizons."""
        return max(self.horizon, self.chase_horizon, s.T_p) + 1

    def plans(self, s: Settings, obs: Observation, warm, compiled: bool = False):
        """(names, Delta (K, H), alpha (K, H), Z (K, 4H)) of every open-loop candidate over the
        horizon H; compiled: their bicycle rollouts by jit_interactive's track (the numbers to rounding),
        as for the sources the compiled core runs."""
        H, y0 = max(self.horizon, s.T_p), obs.z0[1]
        lane_y = s.road.centre(s.road.lane_of(y0))
        towards = np.sign(s.y_ref - lane_y)
        lateral = {"merged": np.full(H, s.y_ref)} if towards == 0 else {
            "wait": np.full(H, lane_y), "lean": np.full(H, lane_y + towards * self.lean),
            **{f"merge after {m}": np.where(np.arange(H) < m, lane_y + towards * self.lean, s.y_ref) for m in self.merge_steps}}
        pace = paces(s, obs.history, H, self.tau_x, self.stream_dv)
        names = [f"{lat}, {p}" for lat in lateral for p in pace]
        y_t = np.array([lateral[lat] for lat in lateral for _ in pace])
        x_t = np.array([x for _ in lateral for _, x in pace.values()])
        v_t = np.array([v for _ in lateral for v, _ in pace.values()])
        v_t = np.where((y_t == s.y_ref) & np.isnan(x_t), entering_speed(s, obs.history), v_t)  # in the lane: its leader's pace
        Delta, alpha, Z = self.track(s, obs.z0, y_t, v_t, x_t, compiled)
        if warm is not None:
            d, a, z = self.shifted(s, obs, warm, H, compiled)
            names = [*names, "shifted"]
            Delta, alpha, Z = np.vstack([Delta, d]), np.vstack([alpha, a]), np.vstack([Z, z])
        return names, Delta, alpha, Z

    def track(self, s: Settings, z0, y_t, v_t, x_t, compiled: bool):
        """strategy.track with this strategy's tau, tau_x and k_y: Delta, alpha (K, H), Z (K, 4H) from z0 (4,) towards
        y_t, v_t, x_t (K, H) in m, m/s, m; compiled: by jit_interactive.track (the numbers to rounding)."""
        if compiled:
            return jit_interactive.track(np.asarray(z0, float), y_t, v_t, x_t, self.tau, self.tau_x, car(s, self.k_y))
        return track(s, z0, y_t, v_t, self.tau, self.k_y, x_t, self.tau_x)

    def shifted(self, s: Settings, obs: Observation, warm, H: int, compiled: bool = False):
        """Delta, alpha (1, H) and Z (1, 4H) of the shifted previous plan, continued beyond T_p as the open-loop
        candidates drive: into the target lane at its leader's pace once the plan ends there, else holding its last y
        and v. So the plan applied last step is judged again whole (a "merge after 3" chosen now is "merge after 2"
        next step, which no other candidate offers); holding its last controls instead would turn the ego in a circle."""
        prev = warm_start(s, obs, warm)
        z_p = simulate(obs.z0, prev.Delta, prev.alpha, s.params)
        if H == s.T_p:
            return prev.Delta[None], prev.alpha[None], z_p[None]
        end = z_p[-4:]
        merged = s.road.lane_of(end[1]) == s.road.lane_of(s.y_ref)
        y_t = np.full((1, H - s.T_p), s.y_ref if merged else end[1])
        v_t = np.full((1, H - s.T_p), entering_speed(s, obs.history) if merged else end[3])
        d, a, z = self.track(s, end, y_t, v_t, np.full_like(y_t, np.nan), compiled)
        return (np.concatenate([prev.Delta, d[0]])[None], np.concatenate([prev.alpha, a[0]])[None],
                np.concatenate([z_p, z[0]])[None])

    def chased(self, s: Settings, obs: Observation, source):
        """(names, Delta (K, H), alpha (K, H), Z (K, 4H), values (K, H, SLOTS, 2)) of the closed-loop candidates
        (Chase), each driven against the predictor's rollout in one batched recursion; for a source the compiled core
        runs, in one compiled call (Chase.compiled)."""
        H, lane_y = max(self.chase_horizon, s.T_p), s.road.centre(s.road.lane_of(obs.z0[1]))
        lean_y = [lane_y + np.sign(s.y_ref - lane_y) * d for d in self.chase_lean]
        combos = [(f"chase gap {g}", f, b, y, c, np.nan) for g, f, b in gaps(s, obs.history) for y in lean_y
                  for c in self.clearance]
        combos += [(f"accept the gap beside at the stream {dv:+.1f} m/s", 0, 0, y, c, dv) for dv in self.accept_dv
                   for y in lean_y for c in self.clearance]
        if not combos or s.road.lane_of(obs.z0[1]) == s.road.lane_of(s.y_ref):
            return [], np.empty((0, H)), np.empty((0, H)), np.empty((0, 4 * H)), np.empty((0, H, *np.shape(obs.history)[1:]))
        _, front, back, lean, clear, dv = zip(*combos)
        policy = Chase(s, obs.z0, list(zip(front, back)), lean, clear, lane_y, self.lane_end, self.tau, self.tau_x,
                       self.align, unseen(s, obs.history), self.k_y, dv)
        params = jit_rollout.values_params(source.predictor)
        if params is None:
            values = source.react(obs.history, policy, H, len(combos))
            Delta, alpha, Z = np.stack(policy.Delta, 1), np.stack(policy.alpha, 1), np.concatenate(policy.Z, 1)
        else:
            Delta, alpha, Z, values = policy.compiled(params, obs.history, H)
        values = self.held(source, obs.history, values)
        names = [f"{what}, lean to {y:.2f} m, enter at {c} m" for what, _, _, y, c, _ in combos]
        return names, Delta, alpha, Z, values

    def predict(self, obs: Observation, source, Z):
        """The predicted values (K, H, SLOTS, 2) under each open-loop candidate's states Z (K, 4H): one batched rollout,
        one compiled call where the predictor's rollout is compiled (jit_rollout.jit_values), whatever the source;
        beyond `trust` steps held (held). The rollout is causal, so it runs only over the steps that are read."""
        ego = Z.reshape(len(Z), -1, 4)[:, :, :2]
        trusted = np.ascontiguousarray(ego[:, :self.read(source, ego.shape[1])])
        rollouts = jit_rollout.jit_values(source.predictor)
        values = source.values(obs.history, trusted) if rollouts is None else rollouts(obs.history, trusted)
        return self.held(source, obs.history, values, ego)

    def read(self, source, H: int) -> int:
        """How many of H rollout steps the verdicts read: `trust` for a learned (`fitted`) predictor, else all H."""
        fitted = self.trust is not None and getattr(source.predictor, "fitted", False)
        return min(self.trust, H) if fitted else H

    def held(self, source, history, values, ego=None):
        """values (K, T, SLOTS, 2) continued to every step of the ego's path ego (K, H, 2) (None: as many as values),
        every other car beyond step `read` going on at its velocity over that step; slot 0 is the ego's own path."""
        H = values.shape[1] if ego is None else ego.shape[1]
        T = self.read(source, H)
        if T == H == values.shape[1]:  # read whole
            return values
        last = values[:, T - 1, 1:]
        before = values[:, T - 2, 1:] if T >= 2 else np.broadcast_to(np.asarray(history, float)[-1, 1:], last.shape)
        out = np.empty((len(values), H, *values.shape[2:]))
        out[:, :T] = values[:, :T]
        out[:, T:, 0] = values[:, T:, 0] if ego is None else ego[:, T:]
        steps = np.arange(1, H - T + 1)[None, :, None, None]
        out[:, T:, 1:] = last[:, None] + steps * (last - before)[:, None]
        return out

    def judge(self, s: Settings, obs: Observation, source, Delta, alpha, Z) -> list[Judged]:
        """The predictor's verdict on each open-loop candidate (K, H) (predict, verdicts)."""
        return self.verdicts(s, obs, self.predict(obs, source, Z), Delta, alpha, Z, compiled(source))

    def verdicts(self, s: Settings, obs: Observation, values, Delta, alpha, Z, compiled: bool = False) -> list[Judged]:
        """The verdict of the predicted values (K, H, SLOTS, 2) on each candidate (K, H); compiled: by
        jit_interactive.verdicts (these numbers, to rounding), as for the sources the compiled core runs."""
        room = self.room(s, values, Z, compiled) if self.wait_by == "room" else np.zeros(len(values))  # by J: never read
        if compiled:
            return self.compiled_verdicts(s, obs, values, Delta, alpha, Z, room)
        K, H = Delta.shape
        ego = Z.reshape(K, H, 4)
        b, brakes = self.foreseen(s, obs, values)
        in_target = np.abs(ego[:, :, 1] - s.y_ref) <= self.merge_tol  # as the episode counts it: astride the line is not in
        merge = np.where(in_target.any(axis=1), in_target.argmax(axis=1) + 1, self.never(s))
        reach = ego[:, :, 0] + ego[:, :, 3] ** 2 / (-2.0 * s.a_box[0]) - self.lane_end
        overrun = np.maximum(0.0, np.where(np.cumsum(in_target, axis=1) == 0, reach, 0.0).max(axis=1))
        Phi_1, Phi_2, Phi_3 = costs(s, obs.u_prev)  # once for all candidates: J_of would build them per candidate
        J = [Phi_1(Delta[k, :s.T_p]) + Phi_2(alpha[k, :s.T_p]) + Phi_3(Z[k, :4 * s.T_p]) for k in range(K)]
        return [Judged(*x) for x in zip(b, brakes, merge, J, overrun, room)]

    @staticmethod
    def room(s: Settings, values, Z, compiled: bool = False):
        """The most room (K,) in m^2 the predicted values (K, H, SLOTS, 2) leave beside each candidate's path Z (K, 4H)
        in the target lane: at each step, the least b_i between the ego put at its x on the target lane's centre and
        the cars in that lane (core.rollout.b_i's shape), then the most of those over the horizon. What a candidate
        that merges within no horizon has to show: the room it is predicted to open, or to meet, for a later merge.
        compiled: by jit_interactive.room (these numbers, to rounding)."""
        if compiled:
            return jit_interactive.room(values, Z, float(s.R), float(s.stretch), float(s.shape), float(s.y_ref),
                                        float(s.road.lane_width), float(s.road.lanes), float(s.road.lane_of(s.y_ref)), FAR)
        K, H = values.shape[:2]
        v = np.array(values, float)
        v[:, :, 0] = np.stack([Z.reshape(K, Z.shape[1] // 4, 4)[:, :H, 0], np.full((K, H), s.y_ref)], -1)
        elsewhere = s.road.lane_of(v[:, :, 1:, 1]) != s.road.lane_of(s.y_ref)
        v[:, :, 1:, 0] += np.where(elsewhere, FAR, 0.0)  # a car outside the target lane leaves room there
        b = b_i(v.reshape(K * H, *v.shape[2:]), s.R, s.stretch, s.shape)  # (N, K H)
        return b.reshape(len(b), K, H).min(axis=0, initial=np.inf).max(axis=1, initial=-np.inf)

    @staticmethod
    def foreseen(s: Settings, obs: Observation, values) -> tuple:
        """(min b_i (K,) m^2, the hardest braking imposed on another car (K,) m/s^2) of predicted values (K, H, SLOTS, 2):
        what a verdict takes from the predictor."""
        K, H = values.shape[:2]
        b = b_i(values.reshape(K * H, *values.shape[2:]), s.R, s.stretch, s.shape)  # (N, K H): every step of every candidate at once
        b = b.reshape(len(b), K, H).min(axis=(0, 2), initial=np.inf)
        return b, braking(values, obs.history, s.params.dt)

    def compiled_verdicts(self, s: Settings, obs: Observation, values, Delta, alpha, Z, room) -> list[Judged]:
        """verdicts in one compiled call (jit_interactive.verdicts), with each candidate's room (K,) m^2."""
        shape = tuple(float(c) for c in (s.R, s.stretch, s.shape, s.params.dt))
        road = (float(s.y_ref), float(self.merge_tol), -2.0 * float(s.a_box[0]), float(self.lane_end), self.never(s))
        forms = tuple((f.P, f.q, float(f.r)) for f in costs(s, obs.u_prev))
        out = jit_interactive.verdicts(values, np.asarray(obs.history, float), Delta, alpha, Z, shape, road, forms, s.T_p)
        return [Judged(*x) for x in zip(*(a.tolist() for a in (*out, room)))]

    @staticmethod
    def acceptable(s: Settings, j: Judged) -> bool:
        """Whether a verdict finds its candidate safe (b_min >= 0, never out of road) and courteous (braking <=
        b_courtesy)."""
        return j.b_min >= 0.0 and j.overrun == 0.0 and (s.b_courtesy is None or j.braking <= s.b_courtesy)

    def order(self, s: Settings, judged: list[Judged]) -> list[int]:
        """Candidates best first: the acceptable ones by the earliest merge, those that merge within no horizon by
        `wait_by` (the most room, or none), then the lowest J; the others after them, the least unsafe first, then the
        least out of road."""
        b_c, never = np.inf if s.b_courtesy is None else s.b_courtesy, self.never(s)
        waiting = lambda j: -j.room if self.wait_by == "room" and j.merge == never else 0.0
        return sorted(range(len(judged)), key=lambda k: (0, judged[k].merge, waiting(judged[k]), judged[k].J) if self.acceptable(s, judged[k])
                      else (1, -min(judged[k].b_min, 0.0), judged[k].overrun, max(judged[k].braking - b_c, 0.0)))

    def ranked(self, s: Settings, obs: Observation, warm, source):
        """Every candidate of both families, best first by the predictor's verdict: (names, Delta (K, T_p), alpha (K, T_p),
        Z (K, 4T_p), verdicts), each in that order."""
        names, Delta, alpha, Z = self.plans(s, obs, warm, compiled(source))
        judged = self.judge(s, obs, source, Delta, alpha, Z)
        c_names, c_Delta, c_alpha, c_Z, c_values = self.chased(s, obs, source)
        judged += self.verdicts(s, obs, c_values, c_Delta, c_alpha, c_Z, compiled(source))
        for other in source.judges:  # each closed-loop candidate as driven against the source, its path then held fixed
            worse = [self.foreseen(s, obs, self.predict(obs, other, z)) for z in (Z, c_Z) if len(z)]
            b, brakes = (np.concatenate(x) for x in zip(*worse))
            judged = [j._replace(b_min=min(j.b_min, w), braking=max(j.braking, a)) for j, w, a in zip(judged, b, brakes)]
        names, T = [*names, *c_names], s.T_p  # the families' horizons differ; the MPC's is shared
        Delta, alpha = np.vstack([Delta[:, :T], c_Delta[:, :T]]), np.vstack([alpha[:, :T], c_alpha[:, :T]])
        Z = np.vstack([Z[:, :4 * T], c_Z[:, :4 * T]])
        k = self.order(s, judged)
        return [names[i] for i in k], Delta[k], alpha[k], Z[k], [judged[i] for i in k]

    def candidates(self, s: Settings, obs: Observation, warm, source) -> list[Start]:
        """The best `refine` candidates of both families (ranked), each as ADMM's start aimed at its own path (its y
        and v at every step of T_p: the refined plan keeps to what the predictor judged, where an aim at its end state
        would let ADMM cut across to it, along the safety shape's edge) and as it is (aim None: the safeguard's check
        only)."""
        names, Delta, alpha, Z, _ = self.ranked(s, obs, warm, source)
        out = []
        for rank in range(min(self.refine, len(names))):
            plan = planned(s, obs.z0, Delta[rank], alpha[rank], Z[rank])
            path = Z[rank].reshape(s.T_p, 4)
            out += [Start(names[rank], plan, replace(s, y_ref=tuple(path[:, 1]), v_ref=tuple(path[:, 3])), rank),
                    Start(f"{names[rank]} as planned", plan, None, rank + 0.5)]
        return out

    def choose(self, s: Settings, obs: Observation, plans):
        """The best-ranked plan whose predicted braking over T_p stays within b_courtesy, else the least braking."""
        b_c = np.inf if s.b_courtesy is None else s.b_courtesy
        return min(plans, key=lambda p: (max(0.0, p[1].braking - b_c), p[0].rank))
