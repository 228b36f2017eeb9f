"""Counterfactual branches of the merge world for the interaction benchmark: held-out branch states and paired ego plans.

A branch state is a world driven by a dataset-style exploratory ego (`data.dataset.explore`) for a random number of steps
to a moment where interaction is possible: the ego before x_ref and not yet in the target lane, a target-lane car within
`reach` metres along the road. From it a pair of ego control sequences (plan A, plan B) over T_p is executed, each in a
deep copy of the world (same drivers, same latched hidden decisions): the ego applies its controls through the bicycle,
the others drive by their own models. The true response of the others is B - A.

World seeds are `seed_offset + k`, k = 0, 1, ...; the dataset's episodes use uniform 32-bit seeds from
np.random.SeedSequence(dataset.seed) (`data.dataset.episode_seeds`), which the job checks are disjoint from these.
"""
from dataclasses import dataclass

import numpy as np

from core.jobs import UserError
from core.rollout import T_OBS
from data import bicycle
from data.dataset import can_interact, episode_seeds, explore
from data.perception import observe
from data.protocol import World
from data.world import steer_to

KINDS = ("push", "speed", "timing")  # back off / push on, slow down / speed up, early / late push


@dataclass
class Pair:
    """One counterfactual pair from a branch state: the shared history and, per plan (A, B), the executed xy (m)."""

    seed: int  # world seed
    step: int  # steps driven before branching
    kind: str  # one of KINDS
    history: np.ndarray  # (T_obs, n_slots+1, 2) what a planner observes at the branch state (data.perception)
    ids: np.ndarray  # (n_slots+1,) the world ids of its slots, ego first
    controls: np.ndarray  # (2, T_p, 2) the ego's [delta (rad), a (m/s^2)] under plan A and B
    xy: np.ndarray  # (2, T_p, n_slots+1, 2) the slots' xy after each step under plan A and B, ego in slot 0
    world: World  # the branch state, for re-drawn counterfactuals

    @property
    def ego(self):
        """The executed ego xy (2, T_p, 2) under plan A and B (m)."""
        return self.xy[:, :, 0]

    @property
    def response(self):
        """True response of the others (T_p, N, 2): their xy under plan B minus under plan A (m)."""
        return self.xy[1, :, 1:] - self.xy[0, :, 1:]


def execute(world: World, controls, ids=None):
    """Drive a copy of `world` with the ego's controls (T_p, 2): xy (T_p, len(ids), 2) of cars `ids` (default every car)
    after each step, and the copy."""
    world = world.copy()
    xy = []
    for u in controls:
        world.step(u)
        xy.append(world.states()[slice(None) if ids is None else ids, :2])
    return np.array(xy), world


def ego_controls(z0, y_targets, v_target, params: bicycle.BicycleParams, k_y, a_bounds):
    """Controls (T_p, 2) that steer the ego alone from state z0 to y_targets[k] (m) at step k and track v_target (m/s).

    Computed on the ego's own bicycle, without the others, so a plan is a fixed control sequence: executed in the world
    the ego follows the same path whatever the others do.
    """
    z, u = np.asarray(z0, dtype=float), []
    for y in y_targets:
        u.append([steer_to(z, y, params, k_y=k_y), float(np.clip(v_target - z[3], *a_bounds))])
        z = bicycle.step(z, np.array(u[-1]), params)
    return np.array(u)


def plan_pair(world: World, kind: str, y_ref: float, T_p: int, rng: np.random.Generator, plans) -> np.ndarray:
    """The ego's controls (2, T_p, 2) of a pair of `kind`; `plans` holds y_push (fraction of y_ref), dv (m/s),
    delay (steps) ranges and the ego's k_y, a_bounds."""
    z0 = world.states()[0]
    y0, v0 = float(z0[1]), float(z0[3])
    own = world.road.centre(world.road.lane_of(y0))
    y_push = float(rng.uniform(*plans.y_push)) * y_ref
    hold, push = np.full(T_p, y0), np.full(T_p, y_push)
    if kind == "push":  # back off to the own lane's centre / push on towards the target lane
        targets = [(np.full(T_p, own), v0), (push, v0)]
    elif kind == "speed":  # slow down / speed up, holding the lateral position
        dv = float(rng.uniform(*plans.dv))
        targets = [(hold, max(0.0, v0 - dv)), (hold, v0 + dv)]
    else:  # timing: push on now / after holding for `delay` steps
        delay = int(rng.integers(plans.delay[0], plans.delay[1] + 1))
        targets = [(push, v0), (np.where(np.arange(T_p) < delay, y0, y_push), v0)]
    return np.stack([ego_controls(z0, y, v, world.params, plans.k_y, tuple(plans.a_bounds)) for y, v in targets])


def branch_state(scenario, policy_ranges, seed: int, branch, rng: np.random.Generator, n_slots: int):
    """(steps driven, world, what the planner sees there: data.perception.Seen) at a random reachable step of seed's
    exploratory episode, or None."""
    candidates = range(branch.min_steps, branch.max_steps + 1)
    _, _, _, copies, _ = explore(scenario, policy_ranges, seed, branch.max_steps + 1, set(candidates))
    ok = [k for k, w in sorted(copies.items()) if can_interact(w, scenario, branch.reach)]
    if not ok:
        return None
    k = int(rng.choice(ok))
    return k, copies[k], observe(copies[k], n_slots, T_OBS)


def heldout_seeds(key: str, start: int, count: int, dataset) -> range:
    """World seeds start .. start + count - 1 (`key`: the setting that chose start); a UserError if any was an episode of
    the dataset (its config: name, seed, episodes)."""
    seeds = range(start, start + count)
    used = sorted(set(episode_seeds(dataset.seed, dataset.episodes)) & set(seeds))
    if used:
        raise UserError(f"{key}={start}: world seeds {used[:5]} are episodes of the dataset {dataset.name} (seed "
                        f"{dataset.seed}, {dataset.episodes} episodes); choose another {key}")
    return seeds


def make_pairs(scenario, policy_ranges, cfg) -> list[Pair]:
    """cfg.states branch states from held-out seeds, one pair of every kind in cfg.plans.kinds from each.

    cfg: seed_offset, states, n_slots, T_p, branch (min_steps, max_steps, reach, tries per state), plans, dataset (seed, episodes).
    """
    seeds = heldout_seeds("seed_offset", cfg.seed_offset, cfg.states * cfg.branch.tries, cfg.dataset)
    pairs, found = [], 0
    for seed in seeds:
        rng = np.random.default_rng([seed, 3])  # the dataset draws from [seed, 1] and [seed, 2]
        state = branch_state(scenario, policy_ranges, seed, cfg.branch, rng, cfg.n_slots)
        if state is None:
            continue
        k, world, seen = state
        for kind in cfg.plans.kinds:
            controls = plan_pair(world, kind, scenario.y_ref, cfg.T_p, rng, cfg.plans)
            xy = np.stack([execute(world, u, seen.ids)[0] for u in controls])
            pairs.append(Pair(seed, k, kind, seen.history, seen.ids, controls, xy, world))
        found += 1
        if found == cfg.states:
            return pairs
    raise UserError(f"only {found} of states={cfg.states} branch states found in {len(seeds)} seeds; "
                    f"raise branch.tries or branch.reach")
