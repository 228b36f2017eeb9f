"""Strategies: which plans a step solves from and which solved plan it applies. A strategy has two methods,
`candidates(s, obs, warm, source) -> [Start]` and `choose(s, obs, plans) -> (Start, StepResult)` over the plans that passed the
safeguard; it is the `mpc.strategy` node of the `planner` config.

- `Paper`: Algorithm 1 as published, one solve from the shifted previous plan.
- `Rules` (mpc=courteous, the engineered baseline): several solves from plans that hold the lane, two hand-written
  behaviour rules (a nominal IDM follower that judges the gap a plan leaves, and `KeepAhead`, which reads a yielding
  driver off the history) and a ranked choice.
- `Interactive` (mpc=interactive): no behaviour rule; generic candidate plans judged by the predictor's rollout alone.
"""
import copy
from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from core.jobs import UserError
from core.validate import Int, ListOf, Real, check_fields, rule
from data.drivers import IDMDriver
from data.world import Steering
from planner import admm, jit_chase, jit_interactive
from planner.mpc import Observation, Settings, car, costs, lane_plans, planned, simulate, warm_start

NONNEG = Real(0)
STOP_MARGIN = 2.0  # m: a chasing candidate keeps able to stop this far before its lane's end, braking as hard as a_box allows
FAR = 1e4  # m: moved this far along the road, a car outside the target lane leaves the room beside a candidate free (jit_interactive.room)
K_PSI = 4.0  # 1/s: a candidate's heading loop (steering), faster than the lateral gain K_Y it serves: a slower one lets a brisk lean overshoot its depth into the safety shape of the car beside
# mpc=interactive's candidates (OpenLoop, ClosedLoop, Chase):
K_Y = 1.2  # 1/s: a candidate's lateral gain: how briskly it leans and crosses, psi_box capping it
TAU = 1.0  # s: time constant of a candidate's speed approaching its target
TAU_X = 2.0  # s: time constant of a gap-targeting candidate closing on the gap's middle
CHASE_HORIZON = 50  # steps of dt over which a closed-loop candidate is judged: long enough to drop back to a later gap
CLEARANCE = (0.0, 0.5, 1.5)  # m: the predicted bumper clearances to both gap cars at which a closed-loop candidate enters
# m/s: closed-loop candidates that lean at the nearby stream's speed plus each (-10: at a standstill) and accept the gap beside
ACCEPT_DV = (-10.0, -3.0, -1.5)
ALIGN = 3.0  # m: a chasing candidate leans only this close to its gap's middle


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


class KeepAhead(NamedTuple):
    """When the nearest target-lane car behind the ego (within `near` m) is seen slowing for it, the lean starts aim at
    that car's speed plus dv instead of their own v, so a driver who yields to the nudge is not overtaken by it (SI)."""

    near: float  # m: how far behind the ego's centre that car's centre may be
    dv: float  # m/s: kept above its speed
    slowing: float  # m/s^2: it counts as slowing once it decelerates harder than this over the last observed steps
    slower: float  # m/s: ... or drives this much slower than the target-lane car ahead of the ego

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


KEEP_AHEAD = KeepAhead(near=6.0, dv=1.0, slowing=0.5, slower=0.7)  # mpc=courteous's keep-ahead of a yielder (SI)
# mpc=courteous's nominal follower, which judges the gap a plan leaves: IDM with the cautious end of the dense drivers'
# headway T (s) and minimum gap s0 (m) (scenario driver_ranges), IDMDriver's defaults otherwise
FOLLOWER = IDMDriver(T=0.5, s0=1.6)
PROGRESS = 0.2  # m: a plan that ends this much nearer y_ref than the ego is now, or in the target lane, merges (Rules.choose)


@dataclass(frozen=True)
class Rules:
    """mpc=courteous's strategy: besides the shifted plan, ADMM solves from holding the lane and aims off it (`starts`,
    each [offset m, a m/s^2, v m/s or None: v_ref]); a lean beside a car seen yielding keeps ahead of it (KEEP_AHEAD);
    the plan applied has the least braking above b_courtesy, predicted or the nominal FOLLOWER's, then merges by the
    lowest J, else waits as the first start says."""

    starts: tuple

    def __post_init__(self):
        for start in self.starts:
            ok = isinstance(start, (list, tuple)) and len(start) == 3 and all(
                isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in start[:2])
            if not ok or not (start[2] is None or (isinstance(start[2], (int, float)) and start[2] >= 0)):
                raise UserError(f"mpc.strategy.starts: {start} must be [offset m, a m/s^2, v m/s >= 0 or null]")

    def candidates(self, s: Settings, obs: Observation, warm, source) -> list[Start]:
        """The shifted plan, ranked after the starts that lean in (offset > 0) and before those that wait in lane (when a
        lean's plan fails or imposes braking, the shifted plan, leaning already, goes on asking the driver behind instead
        of dropping back to the lane centre), then one Start per `starts` entry: ADMM aims at y_ref = the current lane's
        centre moved `offset` towards the scenario's y_ref (0: wait in lane; 1.9: lean in, the nudge) and at v_ref = v
        (None: the scenario's), from holding the lane at a (mpc.lane_plans); a lean beside a car seen yielding aims at
        that car's speed plus KEEP_AHEAD.dv. The target lane's pull would draw every start into one basin; these solves
        stay in theirs (choose)."""
        out = [Start("shifted", warm_start(s, obs, warm), s, sum(float(o) > 0 for o, _, _ in self.starts) + 0.5)]
        lane_y = s.road.centre(s.road.lane_of(obs.z0[1]))
        v_yield = KEEP_AHEAD.speed(s, obs.history)
        plans = zip(*lane_plans(s, obs.z0, [a for _, a, _ in self.starts]))  # held lanes, rolled out together
        for rank, ((offset, _, v), (Delta, alpha, Z)) in enumerate(zip(self.starts, plans), 1):
            y, v = lane_y + float(offset) * np.sign(s.y_ref - lane_y), s.v_ref if v is None else float(v)
            if offset > 0 and v_yield is not None:
                v = float(np.clip(v_yield + KEEP_AHEAD.dv, *s.v_box))
            out.append(Start(f"y {y:+.1f} m, v {v:.1f} m/s", planned(s, obs.z0, Delta, alpha, Z),
                             replace(s, y_ref=y, v_ref=v), rank))
        return out

    def follower_braking(self, s: Settings, obs: Observation, Z, values) -> float:
        """The hardest braking (m/s^2, >= 0) that the nominal FOLLOWER would need behind the ego's plan Z (4T_p,), for
        each other car behind the ego in the plan's lane at a step: there by the predictor's values (T_p, SLOTS, 2), or
        last seen there (the world has a car changing lanes follow the leaders of both). Constant velocity predicts no
        braking; this judges the gap a plan leaves, whoever predicts the positions."""
        ego = Z.reshape(-1, 4)
        x = np.concatenate([obs.history[-1:, 1:, 0], values[:, 1:, 0]])  # (T_p + 1, N), the last observed step first
        v = np.diff(x, axis=0) / s.params.dt  # (T_p, N): along the road, as IDM follows
        lane = s.road.lane_of(ego[:, 1])[:, None]
        there = (s.road.lane_of(values[:, 1:, 1]) == lane) | (s.road.lane_of(obs.history[-1, 1:, 1]) == lane)
        behind = there & (values[:, 1:, 0] < ego[:, :1])
        a = [FOLLOWER.acceleration(v[k, i], ego[k, 0] - values[k, i + 1, 0] - s.road.car_length, ego[k, 3])
             for k, i in zip(*np.nonzero(behind))]
        return float(max(0.0, -min(a, default=0.0)))

    def choose(self, s: Settings, obs: Observation, plans):
        """Among solved (Start, StepResult), each given its follower's braking: the least braking above b_courtesy
        (m/s^2), predicted or the follower's (without courtesy rows, b_safe is not the planner's to judge: none), then a
        merge (a plan that ends in the target lane, or PROGRESS nearer y_ref than the ego) by the lowest cost J;
        without one, the lowest rank, so an ego that cannot merge yet waits as the first start says instead of pressing
        on beside the gap (the scenario's J, which pulls towards y_ref, would choose that), then J."""
        plans = [(st, r._replace(follower_braking=self.follower_braking(s, obs, r.plan.Z, r.values))) for st, r in plans]
        if len(plans) == 1:
            return plans[0]
        y0 = obs.z0[1]
        excess = lambda r: 0.0 if s.b_courtesy is None else max(0.0, r.braking - s.b_courtesy, r.follower_braking - s.b_courtesy)
        merges = lambda r: (s.road.lane_of(r.plan.Z[-3]) == s.road.lane_of(s.y_ref)
                            or abs(s.y_ref - y0) - abs(s.y_ref - r.plan.Z[-3]) >= PROGRESS)
        return min(plans, key=lambda p: (excess(p[1]), (0, p[1].J) if merges(p[1]) else (1, p[0].rank, p[1].J)))


def paces(s: Settings, history, H: int, tau_x: float) -> dict:
    """The longitudinal profiles a candidate may follow over H steps, from the last two observed steps of the history
    (T_obs, SLOTS, 2): {name: (v_target (H,) m/s, x_target (H,) m or NaN: speed only)}. Stopped; the ego's own speed;
    the target lane's mean; and for
    each gap between two consecutive target-lane cars seen, its middle as both cars would move at their observed
    speeds, tracked with time constant tau_x (s): where a merge into that gap would start."""
    x, v, target = seen_target_lane(s, history)
    t = np.arange(1, H + 1) * s.params.dt
    speed = lambda u: (np.full(H, u), np.full(H, np.nan))
    out = {"stop": speed(0.0), "own": speed(v[0])}
    if len(target):
        out["stream"] = speed(max(0.0, v[target].mean()))
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


def steering(s: Settings, k_y: float) -> Steering:
    """A candidate's steering law: lateral gain k_y, heading gain K_PSI (1/s), its heading set-point within psi_box."""
    return Steering(float(k_y), K_PSI, float(s.psi_box[0]), float(s.psi_box[1]), -np.inf, np.inf)


class Chase:
    """K closed-loop candidates, each chasing one gap of the target lane as the predictor moves its cars: the ego's
    speed closes on the gap's middle (time constants TAU, TAU_X in s), never so fast that it could not stop STOP_MARGIN
    before the lane's end braking as hard as a_box allows; within ALIGN m of the middle it leans to lean_y (m) to ask
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

    def __init__(self, s: Settings, z0, gaps, lean_y, clearance, lane_y: float, lane_end: float, unseen, dv, T: int):
        gaps = np.asarray(gaps, np.int64).reshape(-1, 2)
        K, f = len(gaps), float
        self.g = jit_chase.Gaps(
            gaps, np.asarray(dv, f), np.asarray(lean_y, f), np.asarray(clearance, f), *map(f, unseen), f(lane_y),
            f(s.y_ref), f(lane_end - STOP_MARGIN), -2.0 * f(s.a_box[0]), TAU, TAU_X, ALIGN, f(s.params.dt),
            f(s.road.car_length), f(s.road.lane_width), f(s.road.lanes), f(s.road.lane_of(s.y_ref)), self.NEAR,
            self.V_STOPPED, car(s, steering(s, K_Y)), tuple(map(f, self.FOLLOW.following)))
        self.z = np.repeat(np.asarray(z0, f)[None], K, 0)
        self.Delta, self.alpha, self.Z = np.empty((K, T)), np.empty((K, T)), np.empty((K, 4 * T))

    def rows(self, b) -> "Chase":
        """The candidates b (indices) alone, from the same first state (a contingency branch's share)."""
        out = copy.copy(self)
        out.g = self.g._replace(**{f: getattr(self.g, f)[b] for f in ("gaps", "dv", "lean_y", "clearance")})
        out.z, out.Delta, out.alpha, out.Z = (a[b].copy() for a in (self.z, self.Delta, self.alpha, self.Z))
        return out

    def __call__(self, window, k):
        """The egos' xy (K, 2) one step on from the last step of the predicted windows (K, T_obs, SLOTS, 2)."""
        jit_chase.move(np.ascontiguousarray(window, float), window.shape[1], self.z, self.g, k, self.Delta, self.alpha,
                       self.Z)
        return self.z[:, :2].copy()

    def compiled(self, params, history, T: int):
        """Delta, alpha (K, T), Z (K, 4T) and the predicted xy (K, T, SLOTS, 2) of these candidates driven T steps
        against a predictor the compiled core runs (params: jit_rollout.values_params) from the observed history
        (T_obs, SLOTS, 2), in one compiled call (jit_interactive.chase): Source.react(history, self, T, K)'s."""
        return jit_interactive.chase(*params, np.asarray(history, float), self.z, self.g, T)


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


class Judged(NamedTuple):
    """What the predictor's rollout over a candidate's horizon says of it: min b_i (m^2), the hardest braking it
    imposes on another car (m/s^2), the first step it has merged (within merge_tol of y_ref; Judge.never: none), its
    cost J over T_p, how far (m) it runs out of road: past the point from which, not yet merged, it could still
    stop before its lane's end braking as hard as a_box allows (0: never), and the most room (m^2) it is predicted to
    find beside it in the target lane (jit_interactive.room)."""

    b_min: float
    braking: float
    merge: int
    J: float
    overrun: float = 0.0
    room: float = 0.0


@dataclass(frozen=True)
class OpenLoop:
    """The open-loop candidates over `horizon` steps (H = max(horizon, T_p)): wait in lane, lean towards the target lane
    by `lean` (m), or lean and then steer into it after each of `merge_steps`, each with a longitudinal profile (paces:
    stopped, its own speed, the stream's, or closing on the middle of a gap), their speed approaching it with time
    constant TAU (s), closing on a gap's middle with TAU_X (s), steering with lateral gain K_Y (1/s); and the shifted
    previous plan, continued beyond T_p as they drive."""

    lean: float
    merge_steps: tuple
    horizon: int

    def plans(self, s: Settings, obs: Observation, warm):
        """(names, Delta (K, H), alpha (K, H), Z (K, 4H)) of every open-loop candidate."""
        H, y0 = max(self.horizon, s.T_p), obs.z0[1]
        lane_y = s.road.centre(s.road.lane_of(y0))
        towards = np.sign(s.y_ref - lane_y)
        lateral = {"merged": np.full(H, s.y_ref)} if towards == 0 else {
            "wait": np.full(H, lane_y), "lean": np.full(H, lane_y + towards * self.lean),
            **{f"merge after {m}": np.where(np.arange(H) < m, lane_y + towards * self.lean, s.y_ref) for m in self.merge_steps}}
        pace = paces(s, obs.history, H, TAU_X)
        names = [f"{lat}, {p}" for lat in lateral for p in pace]
        y_t = np.array([lateral[lat] for lat in lateral for _ in pace])
        x_t = np.array([x for _ in lateral for _, x in pace.values()])
        v_t = np.array([v for _ in lateral for v, _ in pace.values()])
        v_t = np.where((y_t == s.y_ref) & np.isnan(x_t), entering_speed(s, obs.history), v_t)  # in the lane: its leader's pace
        Delta, alpha, Z = self.track(s, obs.z0, y_t, v_t, x_t)
        if warm is not None:
            d, a, z = self.shifted(s, obs, warm, H)
            names = [*names, "shifted"]
            Delta, alpha, Z = np.vstack([Delta, d]), np.vstack([alpha, a]), np.vstack([Z, z])
        return names, Delta, alpha, Z

    def track(self, s: Settings, z0, y_t, v_t, x_t):
        """Delta, alpha (K, H), Z (K, 4H) of K candidates from z0 (4,) steering to y_t (K, H) m while their speed
        approaches v_t (K, H) m/s, closing on x_t (K, H) m where it is not NaN (jit_interactive.track)."""
        return jit_interactive.track(np.asarray(z0, float), y_t, v_t, x_t, TAU, TAU_X, car(s, steering(s, K_Y)))

    def shifted(self, s: Settings, obs: Observation, warm, H: int):
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
        d, a, z = self.track(s, end, y_t, v_t, np.full_like(y_t, np.nan))
        return (np.concatenate([prev.Delta, d[0]])[None], np.concatenate([prev.alpha, a[0]])[None],
                np.concatenate([z_p, z[0]])[None])


@dataclass(frozen=True)
class ClosedLoop:
    """The closed-loop candidates (Chase) over CHASE_HORIZON steps (at least T_p): for each gap seen in the target lane
    and each of CLEARANCE (m), a policy that leans by `lean` (m) and chases the gap; for each of ACCEPT_DV (m/s) and
    each clearance, one that accepts the gap beside it; each answers the predictor's moves step by step, leaning only
    within ALIGN (m) of its gap's middle, always able to stop before the settings' lane_end (m)."""

    lean: float

    def chased(self, s: Settings, obs: Observation, source, hyp=None):
        """(names (K,), Delta (BK, H), alpha (BK, H), Z (BK, 4H), values (BK, H, SLOTS, 2)) of the K closed-loop
        candidates, each driven against the predictor's rollout (Source.drive); with hypotheses hyp (B, SLOTS), once
        under each (branch-major, in one call), each branch answering as its own feedback from the shared first step."""
        H, lane_y = max(CHASE_HORIZON, s.T_p), s.road.centre(s.road.lane_of(obs.z0[1]))
        y = lane_y + np.sign(s.y_ref - lane_y) * self.lean
        combos = [(f"chase gap {g}", f, b, y, c, np.nan) for g, f, b in gaps(s, obs.history) for c in CLEARANCE]
        combos += [(f"accept the gap beside at the stream {dv:+.1f} m/s", 0, 0, y, c, dv) for dv in ACCEPT_DV
                   for c in CLEARANCE]
        if not combos or s.road.lane_of(obs.z0[1]) == s.road.lane_of(s.y_ref):
            return [], np.empty((0, H)), np.empty((0, H)), np.empty((0, 4 * H)), np.empty((0, H, *np.shape(obs.history)[1:]))
        names = [f"{what}, lean to {y:.2f} m, enter at {c} m" for what, _, _, y, c, _ in combos]
        if hyp is not None:
            combos, source = combos * len(hyp), source.given(np.repeat(hyp, len(combos), 0))
        _, front, back, lean, clear, dv = zip(*combos)
        policy = Chase(s, obs.z0, list(zip(front, back)), lean, clear, lane_y, s.lane_end, unseen(s, obs.history), dv, H)
        return names, *source.drive(obs.history, policy, H)


@dataclass(frozen=True)
class Branches:
    """The hypotheses a contingency step judges every candidate under, from a source that gives them with their
    probabilities (Source.hypotheses; any other is one branch): every combination of yields / does not yield of the
    cars that matter, the nearest first, while at most `most` combinations keep probability >= `p_min`; a car whose
    less probable hypothesis is below p_min, or beyond those, takes its more probable one (not yielding at even odds):
    a plan relies on a yield only where it is judged under both."""

    p_min: float
    most: int

    def of(self, obs: Observation, source):
        """(hypotheses (B, SLOTS), 1: the car yields, or None: one branch; probabilities (B,) summing to 1), the most
        probable first: the source's plain rollout's."""
        if not source.hypotheses:
            return None, np.ones(1)
        p = np.asarray(source.belief(obs.history), float)
        xy = obs.history[-1]
        combos = [(1.0, (p > 0.5).astype(float))]
        for i in np.argsort(np.hypot(*(xy[1:] - xy[0]).T), kind="stable") + 1:
            if min(p[i], 1.0 - p[i]) < self.p_min:
                continue
            split = [(w * q, np.where(np.arange(len(p)) == i, v, h)) for w, h in combos for q, v in ((1 - p[i], 0.0), (p[i], 1.0))]
            kept = [c for c in split if c[0] >= self.p_min]
            if not kept or len(kept) > self.most:
                break
            combos = kept
        combos.sort(key=lambda c: -c[0])  # stable: of equal odds the first made (not yielding)
        w = np.array([c[0] for c in combos])
        return np.array([c[1] for c in combos]), w / w.sum()


BRANCHES = Branches(p_min=0.1, most=4)  # the contingency step's: combinations of probability >= 0.1, at most 4 a step


def merged(judged: list, w) -> list:
    """The verdicts on K candidates from theirs under each of B branches (B*K, branch-major) with probabilities w (B,):
    as unsafe, discourteous and out of road as the worst branch, merging, costing and finding room as their
    probability-weighted mean (their common value where they agree: a merge in no branch stays Judge.never)."""
    def mean(values):
        return values[0] if len(set(values)) == 1 else float(np.dot(w, values))

    K = len(judged) // len(w)
    return [Judged(min(j.b_min for j in js), max(j.braking for j in js), mean([j.merge for j in js]),
                   mean([j.J for j in js]), max(j.overrun for j in js), mean([j.room for j in js]))
            for js in (judged[k::K] for k in range(K))]


@dataclass(frozen=True)
class Judge:
    """The predictor's verdict on candidates (Judged): its rollout read over `trust` steps for a learned (`fitted`)
    predictor (None: all), every other car beyond going on at its last predicted velocity; merged once within the
    settings' merge_tol (m) of y_ref; out of road past the point from which it could no longer stop before `lane_end`
    (m); `never`: the merge step of a candidate that merges within no horizon."""

    lane_end: float
    trust: int | None
    never: int

    def read(self, source, H: int) -> int:
        """How many of H rollout steps the verdicts read: `trust` for a learned (`fitted`) predictor, else all H."""
        fitted = self.trust is not None and getattr(source.predictor, "fitted", False)
        return min(self.trust, H) if fitted else H

    def predict(self, obs: Observation, source, Z):
        """The predicted values (K, H, SLOTS, 2) under each open-loop candidate's states Z (K, 4H): one batched rollout,
        beyond `trust` steps held (held). The rollout is causal, so it runs only over the steps that are read."""
        ego = Z.reshape(len(Z), -1, 4)[:, :, :2]
        trusted = np.ascontiguousarray(ego[:, :self.read(source, ego.shape[1])])
        return self.held(source, obs.history, source.values(obs.history, trusted), ego)

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

    def kernel(self, s: Settings) -> jit_interactive.Judge:
        """What the compiled verdicts read, from the settings s."""
        f = float
        return jit_interactive.Judge(f(s.R), f(s.stretch), f(s.shape), f(s.params.dt), f(s.y_ref), f(s.merge_tol),
                                     -2.0 * f(s.a_box[0]), f(self.lane_end), self.never, f(s.road.lane_width),
                                     f(s.road.lanes), f(s.road.lane_of(s.y_ref)), FAR)

    def verdicts(self, s: Settings, obs: Observation, values, Delta, alpha, Z) -> list[Judged]:
        """The verdict of the predicted values (K, H, SLOTS, 2) on each candidate (K, H) (jit_interactive.verdicts), with
        the most room (m^2) the predictor leaves beside it in the target lane (jit_interactive.room)."""
        j, history = self.kernel(s), np.asarray(obs.history, float)
        room = jit_interactive.room(values, Z, j)
        forms = tuple((f.P, f.q, float(f.r)) for f in costs(s, obs.u_prev))
        out = jit_interactive.verdicts(values, history, Delta, alpha, Z, j, forms, s.T_p)
        return [Judged(*x) for x in zip(*(a.tolist() for a in (*out, room)))]

    @staticmethod
    def acceptable(s: Settings, j: Judged) -> bool:
        """Whether a verdict finds its candidate safe (b_min >= 0, never out of road) and courteous (braking <=
        b_courtesy)."""
        return j.b_min >= 0.0 and j.overrun == 0.0 and (s.b_courtesy is None or j.braking <= s.b_courtesy)

    def order(self, s: Settings, judged: list[Judged]) -> list[int]:
        """Candidates best first: the acceptable ones by the earliest merge, those that merge within no horizon by the
        most room, then the lowest J; the others after them, the least unsafe first, then the least out of road."""
        b_c = np.inf if s.b_courtesy is None else s.b_courtesy
        waiting = lambda j: -j.room if j.merge == self.never else 0.0
        return sorted(range(len(judged)), key=lambda k: (0, judged[k].merge, waiting(judged[k]), judged[k].J) if self.acceptable(s, judged[k])
                      else (1, -min(judged[k].b_min, 0.0), judged[k].overrun, max(judged[k].braking - b_c, 0.0)))


@dataclass(frozen=True)
class Interactive:
    """mpc=interactive: no behaviour rule. Candidates of two families (OpenLoop, ClosedLoop), rolled out by the
    predictor beyond T_p, so a plan that positions for a later merge has a value; each judged by the predictor alone
    (Judge); the best refined by ADMM (Algorithm 1) towards its own path and also offered as it is; the plan applied
    is the first by that order whose step-horizon braking stays within b_courtesy. The settings are the parts'."""

    lean: float = rule(Real(0))  # m: towards the target lane from the current lane's centre
    merge_steps: tuple = rule(ListOf(Int(0), at_least=1))  # steps (of dt) after which a leaning candidate steers into the target lane
    horizon: int = rule(Int(1))  # steps (of dt) over which the predictor judges an open-loop candidate; at least T_p
    trust: int | None = rule(Int(1, nullable=True))  # steps of a learned (`fitted`) predictor's rollout the verdicts read; beyond, every other car goes on at its last predicted velocity (None: all)

    def __post_init__(self):
        check_fields(self, "mpc.strategy")

    @cached_property
    def open_loop(self) -> OpenLoop:
        """The open-loop family."""
        return OpenLoop(self.lean, self.merge_steps, self.horizon)

    @cached_property
    def closed_loop(self) -> ClosedLoop:
        """The closed-loop family."""
        return ClosedLoop(self.lean)

    def judge(self, s: Settings) -> Judge:
        """The judge of both families' candidates under the settings s (its `never`: one past every horizon)."""
        return Judge(s.lane_end, self.trust, max(self.horizon, CHASE_HORIZON, s.T_p) + 1)

    def ranked(self, s: Settings, obs: Observation, warm, source):
        """Every candidate of both families, best first by the predictor's verdict (with hypotheses, merged over the
        branches: Branches, merged): (names, Delta (K, T_p), alpha (K, T_p), Z (K, 4T_p), verdicts), each in that order;
        a closed-loop candidate's plan is its most probable branch's."""
        judge, (hyp, w) = self.judge(s), BRANCHES.of(obs, source)
        names, Delta, alpha, Z = self.open_loop.plans(s, obs, warm)
        B, K = len(w), len(Z)
        tile = lambda a: np.tile(a, (B, 1))
        under = source if hyp is None else source.given(np.repeat(hyp, K, 0))
        judged = merged(judge.verdicts(s, obs, judge.predict(obs, under, tile(Z)), tile(Delta), tile(alpha), tile(Z)), w)
        c_names, c_Delta, c_alpha, c_Z, c_values = self.closed_loop.chased(s, obs, source, hyp)
        judged += merged(judge.verdicts(s, obs, judge.held(under, obs.history, c_values), c_Delta, c_alpha, c_Z), w)
        c_Delta, c_alpha, c_Z = (a[:len(c_names)] for a in (c_Delta, c_alpha, c_Z))  # the most probable branch's
        names, T = [*names, *c_names], s.T_p  # the families' horizons differ; the MPC's is shared
        Delta, alpha = np.vstack([Delta[:, :T], c_Delta[:, :T]]), np.vstack([alpha[:, :T], c_alpha[:, :T]])
        Z = np.vstack([Z[:, :4 * T], c_Z[:, :4 * T]])
        k = judge.order(s, judged)
        return [names[i] for i in k], Delta[k], alpha[k], Z[k], [judged[i] for i in k]

    def candidates(self, s: Settings, obs: Observation, warm, source) -> list[Start]:
        """The best candidate of both families (ranked) as ADMM's start aimed at its own path (its y and v at every step
        of T_p: the refined plan keeps to what the predictor judged, where an aim at its end state would let ADMM cut
        across to it, along the safety shape's edge) and as it is (aim None: the safeguard's check only)."""
        names, Delta, alpha, Z, _ = self.ranked(s, obs, warm, source)
        if not names:
            return []
        plan, path = planned(s, obs.z0, Delta[0], alpha[0], Z[0]), Z[0].reshape(s.T_p, 4)
        return [Start(names[0], plan, replace(s, y_ref=tuple(path[:, 1]), v_ref=tuple(path[:, 3])), 0),
                Start(f"{names[0]} as planned", plan, None, 0.5)]

    def choose(self, s: Settings, obs: Observation, plans):
        """The best-ranked plan whose predicted braking over T_p stays within b_courtesy, else the least braking."""
        b_c = np.inf if s.b_courtesy is None else s.b_courtesy
        return min(plans, key=lambda p: (max(0.0, p[1].braking - b_c), p[0].rank))
