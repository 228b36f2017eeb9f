"""The clairvoyant ceiling: per world, the fastest courteous merge that a search over ego strategies finds on copies of
the true world (true hidden decisions), and the same search with every driver made stubborn (`never_yield`).

What it searches: direct cut-ins (CutInPolicy: wait in the lane or leaning towards the target lane at the stream's
speed plus an offset, turn in at a given step, as a planner without a gap model does); gap acceptance (AcceptPolicy:
wait, down to a standstill, leaning or not, and turn in once the gap beside leaves a clearance or its back car has
stopped for the ego); and gap-targeting feedback policies (GapPolicy): each picks one gap of the target lane (the gap
beside the ego or up to `gaps` gaps ahead or behind), tracks the gap's middle with a speed loop, leans into the target
lane to one of several depths once near the middle, to ask the gap's follower to yield, and enters once both bumper
clearances reach a threshold. In the target lane every policy follows its leader by IDM; none ever reverses. Every policy is rolled out in a
copy of the world until it has merged and kept `settle` more steps without anyone braking harder than b_safe, or fails
(a collision, braking above b_safe, the lane's end, max_steps); a rollout that can no longer beat the best merge found so
far stops early. Each copy drives its own drivers: the world never follows a plan. A diagnostic: it knows what no
planner can (the hidden decisions, by trial), so no planner should ever beat it on a world.

Then the cross-entropy method (`refine`) over the ego's open-loop controls, from the library's refine.starts lowest
scores (its best merge, its nearest misses): perturbed control sequences that turn in and follow once merged. With
`starts` (recorded planner runs' per-step CSVs; a planner batch writes them to <out_dir>/steps/<method>_<seed>.csv, and
`results` passes every batch's to the ceiling on its scenario), each run is replayed open loop on a copy of its world
and counted as it counted itself, a floor the ceiling never falls below, and refined from where it beats the search; the
CSV's `search_*` columns are the search without them.

With blind.episodes > 0 it also reports the best fixed strategy (`blind`): every searched strategy is driven on
blind.episodes other worlds (seeds blind.seed on, never the batch's), and the one with the most courteous merges there
is driven on each world of the batch. A strategy chosen without the hidden decisions: how much of the ceiling is
knowing them.
"""
import itertools
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import hydra
import mlflow
import numpy as np
import pandas as pd
from hydra.core.hydra_config import HydraConfig
from joblib import Parallel, delayed
from omegaconf import DictConfig

from core import stats, validate
from core.jobs import CONF_DIR, UserError, atomic_file, build, console, guarded, mlflow_run, writable
from data import outcomes
from data.bicycle import BicycleParams
from data.drivers import IDMDriver
from data.protocol import World
from data.world import overlap, steer_to
from planner.batch import backend

log = logging.getLogger(__name__)


def stop_speed(x, x_ref):
    """The highest speed (m/s) from which the ego at x (m) still stops 2 m before its lane ends at x_ref, at 2.5 m/s^2."""
    return float(np.sqrt(5.0 * max(0.0, x_ref - 2.0 - x)))


def control(ego, y, a, policy) -> np.ndarray:
    """[delta (rad), a (m/s^2)] that steers the ego towards lateral position y and accelerates at a within the policy's
    bounds, braking no harder than stops it within the step: the ego never reverses."""
    a = float(np.clip(a, max(policy.a_bounds[0], -ego[3] / policy.params.dt), policy.a_bounds[1]))
    return np.array([steer_to(ego, y, policy.params, k_y=policy.k_y), a])


@dataclass(frozen=True)
class GapPolicy:
    """Aim at a target-lane gap, lean in to ask for room, enter when both clearances allow; SI units."""

    y_ref: float  # target lane centre (m)
    x_ref: float  # the ego's lane ends here (m)
    gap: int  # 0: the gap the ego is beside at the start, +k: k gaps ahead, -k: k gaps behind
    y_lean: float  # lateral position held while asking for room (m)
    clearance: float  # bumper clearance to both gap cars needed to enter (m)
    car_length: float  # m
    params: BicycleParams
    align: float = 3.0  # lean only within this distance of the gap's middle (m)
    k_x: float = 0.5  # speed set-point per metre from the gap's middle (1/s)
    k_v: float = 1.5  # speed loop gain (1/s)
    k_y: float = 0.6  # lateral gain of the steering law (1/s, data.world.steer_to)
    a_bounds: tuple = (-4.0, 2.0)  # the ego's acceleration limits (m/s^2)
    follow: IDMDriver = field(default_factory=lambda: IDMDriver(T=0.6, s0=1.5, a_max=2.0, b=3.0))  # in the target lane

    def pick(self, z):
        """(front id or None, back id or None): this policy's gap among the target-lane cars of states z (M, 4)."""
        ids = np.flatnonzero(np.abs(z[1:, 1] - self.y_ref) < 2.0) + 1
        ids = ids[np.argsort(-z[ids, 0])]  # front to back
        k = int(np.sum(z[ids, 0] > z[0, 0])) - self.gap  # gap k lies between ids[k-1] and ids[k]
        return (int(ids[k - 1]) if 0 < k <= len(ids) else None), (int(ids[k]) if 0 <= k < len(ids) else None)

    @property
    def name(self):
        """How the search reports this strategy."""
        return f"gap {self.gap:+d}, lean {self.y_lean} m, clearance {self.clearance} m"

    def __call__(self, z, target, k):
        """Control [delta (rad), a (m/s^2)] at step k in states z (M, 4) towards the gap target = (front id, back id)."""
        ego, (front, back) = z[0], target
        x_front = z[front, 0] if front is not None else ego[0] + 60.0
        x_back = z[back, 0] if back is not None else ego[0] - 60.0
        v_gap = float(np.mean([z[i, 3] for i in target if i is not None] or [ego[3]]))
        room_front, room_back = x_front - ego[0] - self.car_length, ego[0] - x_back - self.car_length
        if abs(ego[1] - self.y_ref) < 1.0:  # in: follow the leader
            a, y = (self.follow.acceleration(ego[3], room_front, z[front, 3]) if front is not None
                    else self.follow.acceleration(ego[3])), self.y_ref
        else:
            middle = 0.5 * (x_front + x_back)
            a = self.k_v * (min(v_gap + self.k_x * (middle - ego[0]), stop_speed(ego[0], self.x_ref)) - ego[3])
            if min(room_front, room_back) >= self.clearance:
                y = self.y_ref
            else:
                y = self.y_lean if abs(middle - ego[0]) <= self.align else 0.0
        return control(ego, y, a, self)


@dataclass(frozen=True, kw_only=True)
class TurnIn:
    """What every policy without a chosen gap shares: once turned in, follow the target lane's leader by IDM; SI units."""

    y_ref: float  # target lane centre (m)
    x_ref: float  # the ego's lane ends here (m)
    car_length: float  # m
    params: BicycleParams
    k_y: float = 2.0  # lateral gain of the steering law (1/s)
    a_bounds: tuple = (-4.0, 3.0)  # the ego's acceleration limits (m/s^2): the planner's mpc.a_box
    follow: IDMDriver = field(default_factory=lambda: IDMDriver(T=0.6, s0=1.5, a_max=2.0, b=3.0))

    def pick(self, z):
        """No gap chosen in advance: whatever is beside the ego when it turns."""
        return None

    def around(self, z):
        """(target-lane mask (M-1,), leader id or None, ids behind the ego) in states z (M, 4)."""
        ego = z[0]
        lane = np.abs(z[1:, 1] - self.y_ref) < 2.0
        ahead, behind = (np.flatnonzero(lane & side) + 1 for side in (z[1:, 0] > ego[0], z[1:, 0] <= ego[0]))
        return lane, (ahead[np.argmin(z[ahead, 0])] if len(ahead) else None), behind

    def enter(self, z, leader):
        """(y (m), a (m/s^2)) once turned in: the target lane's centre behind its leader."""
        ego = z[0]
        if leader is None:
            return self.y_ref, self.follow.acceleration(ego[3])
        return self.y_ref, self.follow.acceleration(ego[3], z[leader, 0] - ego[0] - self.car_length, z[leader, 3])


@dataclass(frozen=True, kw_only=True)
class WaitThenEnter(TurnIn):
    """What a cut-in and gap acceptance share: hold y_wait at the nearby stream's speed plus dv (never below v_floor)
    while waiting, and once turned in follow the target lane's leader by IDM; SI units."""

    y_wait: float  # lateral position held while waiting: the lane centre, or leaning in to ask for room (m)
    dv: float  # speed relative to the nearby target-lane cars while waiting (m/s)
    v_floor: float = -np.inf  # the lowest waiting speed (m/s)
    k_v: float = 1.5  # speed loop gain (1/s)

    def wait(self, z, lane):
        """(y (m), a (m/s^2)) while waiting."""
        ego = z[0]
        near = lane & (np.abs(z[1:, 0] - ego[0]) < 15.0)
        v_des = max(self.v_floor, (z[1:][near, 3].mean() if near.any() else ego[3]) + self.dv)
        return self.y_wait, self.k_v * (min(v_des, stop_speed(ego[0], self.x_ref)) - ego[3])


@dataclass(frozen=True, kw_only=True)
class CutInPolicy(WaitThenEnter):
    """Wait until step `enter`, then steer straight into the target lane: the direct cut-in that a planner without a
    gap model makes, and the nudge-then-cut-in of one that leans first; SI units."""

    enter_at: int  # the step at which the ego turns in

    @property
    def name(self):
        """How the search reports this strategy."""
        return f"cut in at step {self.enter_at}, stream speed {self.dv:+.1f} m/s, waiting at y = {self.y_wait} m"

    def __call__(self, z, target, k):
        """Control [delta (rad), a (m/s^2)] at step k in states z (M, 4)."""
        lane, leader, _ = self.around(z)
        y, a = self.enter(z, leader) if k >= self.enter_at else self.wait(z, lane)
        return control(z[0], y, a, self)


@dataclass(frozen=True, kw_only=True)
class AcceptPolicy(WaitThenEnter):
    """Wait (down to a standstill: a large negative dv) and turn in as soon as the gap beside the ego leaves `clearance`
    to its front car and to its back car, or its back car has stopped for it; committed once its centre is over the
    lane line: gap acceptance, as a driver waiting at a lane's end does; SI units."""

    clearance: float  # bumper clearance to the gap's front and back cars needed to turn in (m)
    v_stopped: float = 0.5  # a back car this slow has stopped for the ego (m/s)
    v_floor: float = 0.0
    follow: IDMDriver = field(default_factory=lambda: IDMDriver(T=0.6, s0=1.0, a_max=3.0, b=3.0))

    @property
    def name(self):
        """How the search reports this strategy."""
        return f"accept a gap of {self.clearance} m, stream speed {self.dv:+.1f} m/s, waiting at y = {self.y_wait} m"

    def __call__(self, z, target, k):
        """Control [delta (rad), a (m/s^2)] at step k in states z (M, 4)."""
        ego = z[0]
        lane, leader, behind = self.around(z)
        room_front = z[leader, 0] - ego[0] - self.car_length if leader is not None else np.inf
        room_back = ego[0] - z[behind, 0].max() - self.car_length if len(behind) else np.inf
        lag_gone = room_back >= self.clearance or z[behind[np.argmax(z[behind, 0])], 3] <= self.v_stopped
        turned = abs(ego[1] - self.y_ref) < 2.0 or (room_front >= self.clearance and lag_gone)
        y, a = self.enter(z, leader) if turned else self.wait(z, lane)
        return control(ego, y, a, self)


@dataclass(frozen=True, eq=False)
class OpenLoop(TurnIn):
    """Given controls applied open loop (steering within delta_max, braking never reversing the ego) until the ego is in
    the target lane or they run out, then turn in and follow the leader: a refined plan; SI units."""

    controls: np.ndarray  # (steps, 2) [delta (rad), a (m/s^2)]
    merge_tol: float  # in the target lane once this close to its centre (m)
    label: str  # how the search reports it
    delta_max: float = 0.5  # rad: the steering law's bound and the planner's mpc.delta_box

    @property
    def name(self):
        """How the search reports this strategy."""
        return self.label

    def __call__(self, z, target, k):
        """Control [delta (rad), a (m/s^2)] at step k in states z (M, 4)."""
        ego = z[0]
        if k < len(self.controls) and abs(ego[1] - self.y_ref) > self.merge_tol:
            delta, a = self.controls[k]
            a = min(max(a, self.a_bounds[0], -ego[3] / self.params.dt), self.a_bounds[1])
            return np.array([min(max(delta, -self.delta_max), self.delta_max), a])
        y, a = self.enter(z, self.around(z)[1])
        return control(ego, y, a, self)


@dataclass(frozen=True, eq=False)
class Outcome:
    """A rollout's result: courteous merge or not, t_merge (steps; max_steps if none), the braking it imposed (m/s^2),
    the strategy, the controls it applied (steps, 2) and, for a failure, how far it ended from a courteous merge (`miss`:
    its lateral distance from the target lane beyond merge_tol in m, plus the braking it imposed beyond b_safe in m/s^2,
    plus b_max for a collision; 0 for a courteous merge)."""

    courteous: bool
    t_merge: int
    b_imposed: float
    policy: str
    controls: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    miss: float = 0.0

    @property
    def score(self):
        """Lower is better: t_merge (steps) for a courteous merge, max_steps plus the miss for a failure."""
        return self.t_merge + self.miss


def better(a: Outcome | None, b: Outcome) -> Outcome:
    """The better of two outcomes: a courteous merge over none, then the sooner one; of two failures, the one that imposed
    less braking; a tie keeps `a`."""
    if a is None or (b.courteous and (not a.courteous or b.t_merge < a.t_merge)):
        return b
    return b if not a.courteous and not b.courteous and b.b_imposed < a.b_imposed else a


def rollout(world: World, policy, scenario, max_steps, settle, best=None) -> Outcome:
    """Drive a copy of `world` with `policy`; stops at failure, after `settle` steps past the merge, or once it cannot
    merge before step `best`."""
    w = world.copy()
    z = w.states()
    target = policy.pick(z)
    states, controls, t_merge, name = [z], [], None, policy.name
    limit = max_steps if best is None else min(max_steps, best - 1)
    for k in range(1, max_steps + 1):
        controls.append(policy(z, target, k - 1))
        hits = w.step(controls[-1])
        z = w.states()
        states.append(z)
        b = outcomes.b_imposed_max(states[-2:], w.params.dt)
        hit = any(0 in pair for pair in hits)
        if hit or b > scenario.b_safe or (t_merge is None and (z[0, 0] >= scenario.x_ref or k > limit)):
            miss = max(0.0, abs(z[0, 1] - scenario.y_ref) - scenario.merge_tol) + max(0.0, b - scenario.b_safe) + hit * scenario.b_max
            return Outcome(False, max_steps, outcomes.b_imposed_max(states, w.params.dt), name, np.array(controls), miss)
        if t_merge is None and abs(z[0, 1] - scenario.y_ref) <= scenario.merge_tol:
            t_merge = k
        if t_merge is not None and k >= t_merge + settle:
            break
    ok = t_merge is not None
    miss = 0.0 if ok else max(0.0, abs(z[0, 1] - scenario.y_ref) - scenario.merge_tol)
    return Outcome(ok, t_merge if ok else max_steps, outcomes.b_imposed_max(states, w.params.dt), name, np.array(controls), miss)


def replay(world: World, controls, scenario, max_steps) -> Outcome:
    """A recorded run's controls (steps, 2) applied open loop on a copy of `world`, judged as the run itself was
    (planner.report.metrics): courteous when it was in the target lane before x_ref, nothing collided with the ego and
    nobody braked harder than b_safe over the steps it drove; t_merge its first step in the lane (max_steps if none)."""
    w = world.copy()
    states = [w.states()]
    hit = any(overlap(states[0][0], z, w.road) for z in states[0][1:])
    for u in np.asarray(controls, float):
        hit |= any(0 in pair for pair in w.step(u))
        states.append(w.states())
    states = np.array(states)
    in_lane = np.flatnonzero((np.abs(states[1:, 0, 1] - scenario.y_ref) <= scenario.merge_tol)
                             & (states[1:, 0, 0] < scenario.x_ref)) + 1
    b = outcomes.b_imposed_max(states, w.params.dt)
    ok = bool(outcomes.courteous(len(in_lane), hit, b, scenario.b_safe))
    return Outcome(ok, int(in_lane[0]) if ok else max_steps, b, "a recorded run, replayed", np.asarray(controls, float))


def refine(world: World, start: Outcome, scenario, cfg, rng: np.random.Generator, best: Outcome | None) -> Outcome:
    """The cross-entropy method over the ego's open-loop controls around start.controls, on copies of `world`: per
    iteration, refine.samples perturbations (Gaussian at knots every refine.knot steps, linear between) driven as
    OpenLoop plans that turn in once merged, the refine.elites lowest scores setting the next mean and spread; returns
    the better of `best` and every plan it drove (rollouts that cannot beat `best` stop early)."""
    r = cfg.refine
    steps = np.arange(len(start.controls))
    knots = np.arange(0, len(steps) + r.knot, r.knot)
    mean, spread = np.zeros((len(knots), 2)), np.tile(np.asarray(r.sigma, float), (len(knots), 1))
    common = dict(y_ref=scenario.y_ref, x_ref=scenario.x_ref, car_length=scenario.road.car_length,
                  params=scenario.params, merge_tol=scenario.merge_tol, label=f"refined from: {start.policy}")
    for _ in range(r.iterations):
        noise = rng.normal(mean, spread, (r.samples, *mean.shape))
        plans = [start.controls + np.stack([np.interp(steps, knots, e[:, j]) for j in range(2)], -1) for e in noise]
        outs = [rollout(world, OpenLoop(controls=u, **common), scenario, cfg.max_steps, cfg.search.settle,
                        best.t_merge if best is not None and best.courteous else None) for u in plans]
        for o in outs:
            best = better(best, o)
        elite = noise[np.argsort([o.score for o in outs], kind="stable")[: r.elites]]
        mean, spread = elite.mean(0), elite.std(0)
    return best


def policies(scenario, search) -> list:
    """The searched strategies: direct cut-ins at every waiting position, entry step and speed offset; gap acceptance
    at every waiting position, speed offset and clearance; every gap within search.gaps of the ego's with every lean
    depth and clearance."""
    gaps = range(-search.gaps, search.gaps + 1)
    length, params = scenario.road.car_length, scenario.params
    common = dict(y_ref=scenario.y_ref, x_ref=scenario.x_ref, car_length=length, params=params)
    cut_ins = [CutInPolicy(enter_at=e, dv=dv, y_wait=y, **common)
               for y, e, dv in itertools.product(search.y_wait, search.enter, search.dv)]
    accepts = [AcceptPolicy(y_wait=y, dv=dv, clearance=c, **common)
               for y, dv, c in itertools.product(search.y_wait, search.accept_dv, search.clearance)]
    return cut_ins + accepts + [GapPolicy(scenario.y_ref, scenario.x_ref, g, y, c, length, params)
                                for g, y, c in itertools.product(gaps, search.y_lean, search.clearance)]


def library(world: World, scenario, cfg) -> list:
    """Every strategy of policies() driven on copies of `world`, cut-ins first (quick merges bound the rest early): their
    outcomes, in that order."""
    best, outs = None, []
    for p in policies(scenario, cfg.search):
        outs.append(rollout(world, p, scenario, cfg.max_steps, cfg.search.settle,
                            best.t_merge if best is not None and best.courteous else None))
        best = better(best, outs[-1])
    return outs


def search_world(world: World, scenario, cfg, rng: np.random.Generator | None = None, starts=()) -> tuple:
    """(the search alone, the final value) on copies of `world`: the best of the strategy library (policies()) and, with
    `rng` and refine.starts > 0, of its refinement (refine) from the library's refine.starts lowest scores; then each
    recorded run in `starts` (controls (steps, 2)) replayed open loop, and refined from where it beats the search."""
    outs = library(world, scenario, cfg)
    best = None
    for o in outs:
        best = better(best, o)
    if rng is not None:
        for o in sorted(outs, key=lambda o: o.score)[: cfg.refine.starts]:
            best = refine(world, o, scenario, cfg, rng, best)
    alone = best
    for controls in starts:
        run = replay(world, controls, scenario, cfg.max_steps)
        if better(best, run) is run:  # the run beats everything so far: it is the floor, and a start worth refining
            best = run if rng is None else refine(world, run, scenario, cfg, rng, run)
    return alone, best


def held_in_lane(world: World, scenario, steps) -> float:
    """The largest braking (m/s^2) of any other car over `steps` with the ego kept in its lane, stopping before its end:
    what the world does without the ego's doing (calibration: at most 2 m/s^2)."""
    w = world.copy()
    states = [w.states()]
    for _ in range(steps):
        z = states[-1][0]
        a = np.clip(stop_speed(z[0], scenario.x_ref) - z[3], -4.0, 1.0)
        w.step(np.array([steer_to(z, scenario.road.centre(0), scenario.params), a]))
        states.append(w.states())
    return outcomes.b_imposed_max(np.array(states), scenario.params.dt)


def courteous_strategies(scenario, cfg, seed: int) -> np.ndarray:
    """Whether each strategy of policies() merges courteously on world `seed` (no early stop: every one is driven)."""
    world = scenario.make_world(seed)
    return np.array([rollout(world, p, scenario, cfg.max_steps, cfg.search.settle).courteous
                     for p in policies(scenario, cfg.search)])


def blind_strategy(scenario, cfg):
    """The strategy of policies() with the most courteous merges on the blind worlds (seeds blind.seed on), and that
    share."""
    seeds = range(cfg.blind.seed, cfg.blind.seed + cfg.blind.episodes)
    hits = np.mean(Parallel(n_jobs=cfg.n_jobs)(delayed(courteous_strategies)(scenario, cfg, s) for s in seeds), axis=0)
    best = int(np.argmax(hits))
    return policies(scenario, cfg.search)[best], float(hits[best])


def ceiling(scenario, cfg, seed: int, blind=None, starts=()) -> dict:
    """One world's row: the search with its true hidden decisions (given `starts`, recorded runs' controls (steps, 2) on
    this world, those too) and with every driver stubborn, and the braking the world shows with the ego held in its lane;
    with `blind` (a strategy of policies()), its outcome too. `search_*`: the true world's search alone, without the
    starts; `cpu_seconds`: the world's processor time (s), what it costs on an idle core."""
    t0 = time.process_time()
    world = scenario.make_world(seed)
    rng = np.random.default_rng([cfg.refine.seed, seed])  # one stream per world: the same rows on any backend
    alone, true = search_world(world, scenario, cfg, rng, starts)
    nobody = np.zeros(len(world.states()), bool)
    # where nobody yields (every highway-env world) the stubborn world is the true one: its search would repeat this one
    stubborn = alone if not world.decisions().any() else search_world(world.with_decisions(nobody), scenario, cfg, rng)[1]
    row = {"seed": seed, "ceiling_courteous": float(true.courteous), "ceiling_t_merge": float(true.t_merge),
           "ceiling_b_imposed": true.b_imposed, "ceiling_policy": true.policy,
           "search_courteous": float(alone.courteous), "search_t_merge": float(alone.t_merge), "starts": len(starts),
           "never_yield_courteous": float(stubborn.courteous), "never_yield_t_merge": float(stubborn.t_merge),
           "never_yield_b_imposed": stubborn.b_imposed, "never_yield_policy": stubborn.policy,
           "held_b_imposed": held_in_lane(world, scenario, cfg.max_steps)}
    if blind is not None:
        fixed = rollout(world, blind, scenario, cfg.max_steps, cfg.search.settle)
        row.update({"blind_courteous": float(fixed.courteous), "blind_t_merge": float(fixed.t_merge),
                    "blind_b_imposed": fixed.b_imposed, "blind_policy": fixed.policy})
    return {**row, "cpu_seconds": time.process_time() - t0}


def aggregate(rows) -> dict:
    """The batch's rates (Wilson 95%) and mean t_merge over courteous worlds (Student t 95%) for both searches, and for
    the best fixed strategy where the rows have it; the share of worlds where the search alone reached the final value
    (`search_reached`), and the mean processor time per world (s)."""
    held = np.array([r["held_b_imposed"] for r in rows], float)
    reached = [r["search_courteous"] == r["ceiling_courteous"] and r["search_t_merge"] == r["ceiling_t_merge"] for r in rows]
    out = {"worlds": float(len(rows)), "held_b_imposed_max": float(held.max(initial=0.0)),
           "held_calm": float(np.mean(held <= 2.0)) if len(held) else float("nan"),
           "search_reached": float(np.mean(reached)) if rows else float("nan"),
           "cpu_seconds": float(np.mean([r["cpu_seconds"] for r in rows])) if rows else float("nan")}
    for k in ["ceiling", "never_yield"] + (["blind"] if rows and "blind_courteous" in rows[0] else []):
        hits = np.array([r[f"{k}_courteous"] for r in rows], float)
        out[f"{k}_courteous"] = float(hits.mean()) if len(hits) else float("nan")
        out[f"{k}_courteous_lo"], out[f"{k}_courteous_hi"] = stats.wilson(float(hits.sum()), len(hits))
        t = [r[f"{k}_t_merge"] for r in rows if r[f"{k}_courteous"]]
        out[f"{k}_t_merge"], out[f"{k}_t_merge_lo"], out[f"{k}_t_merge_hi"] = stats.mean_ci(t)
    return out


def recorded(templates, seeds) -> dict:
    """{seed: [controls (steps, 2), ...]}: the columns delta (rad) and a (m/s^2) of the per-step CSV at each template
    with {seed} filled in, where it exists; one line for a template without {seed} or that names no file of these
    worlds, and for a file without those columns."""
    out = {s: [] for s in seeds}
    for t in templates:
        if "{seed}" not in t:
            raise UserError(f"starts: {t} has no {{seed}}: each world needs its own run's per-step CSV")
        paths = {s: Path(t.replace("{seed}", str(s))) for s in seeds}
        found = {s: p for s, p in paths.items() if p.is_file()}
        if not found:
            raise UserError(f"starts: {t} names no file for seeds {seeds[0]}..{seeds[-1]}")
        for s, path in found.items():
            steps = pd.read_csv(path)
            if not {"delta", "a"} <= set(steps.columns):
                raise UserError(f"{path}: no delta and a columns; starts must be a planner run's per-step CSV "
                                "(planner/report.py write_csv)")
            out[s].append(steps[["delta", "a"]].to_numpy(float))
    return out


SEARCH = {"refine.starts": validate.Int(0), "refine.iterations": validate.Int(1), "refine.samples": validate.Int(1),
          "refine.elites": validate.Int(1), "refine.knot": validate.Int(1), "refine.seed": validate.SEED,
          "refine.sigma": validate.ListOf(validate.NONNEG, length=2), "starts": validate.ListOf(validate.Text()),
          "backend": validate.OneOf(("loky", "ray")), "ray.address": validate.Text(nullable=True)}  # the refinement's keys


def check(cfg):
    """One line for a setting the search cannot honour: a world other than the reactive one, too small a search, blind
    worlds among the batch's, more elites than samples."""
    validate.check(cfg, "ceiling")
    validate.check(cfg, SEARCH)
    if cfg.world != "reactive":
        raise UserError(f"world={cfg.world}: the ceiling searches copies of the true world; it needs world=reactive")
    if cfg.refine.elites > cfg.refine.samples:
        raise UserError(f"refine.elites={cfg.refine.elites}: more than the {cfg.refine.samples} samples it picks from")
    blind = range(cfg.blind.seed, cfg.blind.seed + cfg.blind.episodes)
    if set(blind) & set(range(cfg.seed, cfg.seed + cfg.episodes)):
        raise UserError(f"blind.seed={cfg.blind.seed}: its {cfg.blind.episodes} worlds overlap the batch's (seed "
                        f"{cfg.seed}, {cfg.episodes} episodes); the strategy must be chosen on other worlds")


@guarded
def run(cfg: DictConfig) -> dict:
    """Search cfg.episodes worlds (seeds cfg.seed on) in parallel on cfg.backend (planner.batch.backend: local joblib
    processes or Ray); per-world CSV, MLflow run (experiment `ceiling`)."""
    check(cfg)
    scenario = build(cfg.scenario)
    out_dir = writable(Path(cfg.out_dir or HydraConfig.get().runtime.output_dir), "out_dir")
    seeds = list(range(cfg.seed, cfg.seed + cfg.episodes))
    starts = recorded(cfg.starts, seeds)
    with backend(cfg):
        blind, blind_share = blind_strategy(scenario, cfg) if cfg.blind.episodes else (None, None)
        with mlflow_run("ceiling", cfg, run_name=f"ceiling-{scenario.name}", scenario=scenario.name, seed=cfg.seed):
            rows = Parallel(n_jobs=cfg.n_jobs)(delayed(ceiling)(scenario, cfg, s, blind, starts[s]) for s in seeds)
            csv_path = out_dir / f"ceiling_{scenario.name}.csv"
            atomic_file(csv_path, lambda p: pd.DataFrame(rows).to_csv(p, index=False))
            r = aggregate(rows)
            mlflow.log_metrics(r if blind is None else {**r, "blind_choice_share": blind_share})
            mlflow.log_artifact(str(csv_path))
    ci = lambda k, f: f"{r[k]:{f}} [{r[k + '_lo']:{f}}, {r[k + '_hi']:{f}}]"
    log.info(f"{scenario.name}, {len(rows)} worlds from seed {cfg.seed} (95% intervals): courteous merge "
             f"{ci('ceiling_courteous', '.1%')} in {ci('ceiling_t_merge', '.1f')} steps; never yield "
             f"{ci('never_yield_courteous', '.1%')} in {ci('never_yield_t_merge', '.1f')} steps; ego held in its lane: others "
             f"brake at most {r['held_b_imposed_max']:.2f} m/s^2; the search alone reached the final value in "
             f"{r['search_reached']:.1%} of worlds ({sum(len(v) for v in starts.values())} recorded runs as starts); "
             f"{r['cpu_seconds']:.1f} processor seconds per world; per world: {csv_path}")
    if blind is not None:
        log.info(f"best fixed strategy on the {cfg.blind.episodes} worlds from seed {cfg.blind.seed} "
                 f"({blind.name}: {blind_share:.1%} there): courteous merge "
                 f"{ci('blind_courteous', '.1%')} here")
    return r


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="ceiling")
def hydra_main(cfg: DictConfig) -> None:
    run(cfg)


def main() -> None:
    """Entry point of the `ceiling` console script: overrides checked first (one line for a misspelt key)."""
    console("ceiling", hydra_main)
