"""Closed loop: plan, apply the first control to the nonlinear bicycle, let the others move, observe; record every step.

The others move by the world's own reactive drivers (`world=reactive`) or by the predictor (`world=predictor`, as in
the paper). The planner sees the world through data.perception.observe: the n_slots nearest cars' observed histories,
extrapolated at constant velocity before t = 0.
"""
import time
from dataclasses import dataclass, field

import numpy as np

from core.jobs import UserError, check_stopped
from data import outcomes
from data.perception import observe
from data.protocol import World
from data.world import overlap


def check_others(world: World, others: str, n_slots: int) -> None:
    """One UserError, before the first step, unless the predictor can move the others (world=predictor): it must see
    every other car (n_slots of them)."""
    cars = len(world.states()) - 1
    if others == "predictor" and n_slots != cars:
        raise UserError(f"world=predictor moves every car with the predictor, but it sees n_slots={n_slots} of the "
                        f"{cars} other cars; set n_slots={cars} (a model trained for it) or use world=reactive")


def predictor_move(world: World, history, ids, ego_u, source):
    """Advance dt with the ego on the bicycle and every other car where the predictor puts it (one step from history,
    slots `ids`: every other car, check_others); returns collided pairs."""
    nxt = source.values(history, np.zeros((1, 1, 2)))[0, 0]  # one step; the ego slot is not used
    return world.move(ego_u, nxt[1:])


@dataclass
class Episode:
    """A driven episode: states (T+1, M, 4), applied controls (T, 2), one record per MPC step, notes."""

    states: list = field(default_factory=list)
    controls: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    collided: bool = False


def drive(world: World, planner, source, x_ref, target_lane, T_obs, max_steps, others, n_slots):
    """Run planner(obs, warm) -> StepResult until the ego passes x_ref or max_steps; never raises for a bad step, but
    stops (Stopped) after a step during which a stop signal arrived, even if the step caught its exception.

    T_obs: observed steps; n_slots: the other cars the predictor sees (data.perception); others: "reactive" (the world's
    drivers) or "predictor" (moved by `source`)."""
    from planner.mpc import Observation

    check_others(world, others, n_slots)
    z = world.states()
    ep = Episode(states=[z])
    start_hits = [j for j in range(1, len(z)) if overlap(z[0], z[j], world.road)]
    if start_hits:
        ep.notes.append(f"start in collision with car(s) {start_hits}")
        ep.collided = True
    u_prev, warm = np.zeros(2), None
    for k in range(max_steps):
        if z[0, 0] >= x_ref:
            break
        seen = observe(world, n_slots, T_obs)
        obs = Observation(z[0].copy(), u_prev.copy(), seen.history)
        if source.needs_world:  # gradients=oracle: the world itself, a diagnostic ceiling
            source.predictor.world, source.predictor.ids = world, seen.ids
        t0 = time.perf_counter()
        result = planner(obs, warm)
        step_ms = 1e3 * (time.perf_counter() - t0)
        check_stopped()  # a step falls back on any error, also on one a stop signal caused inside its solver
        u = np.nan_to_num(result.u)
        hits = world.step(u) if others == "reactive" else predictor_move(world, seen.history, seen.ids, u, source.at(seen.history))
        if any(0 in pair for pair in hits):
            ep.collided = True
        braking = outcomes.b_imposed_max([z, world.states()], world.params.dt)  # this step's, m/s^2
        z = world.states()
        u_prev, warm = u, result.plan
        ep.states.append(z)
        ep.controls.append(u)
        lane = int(world.road.lane_of(z[0, 1]))
        ep.rows.append({"step": k + 1, "time_s": round(world.t, 6), "x": z[0, 0], "y": z[0, 1],
                        "psi": z[0, 2], "v": z[0, 3], "delta": u[0], "a": u[1], "lane": lane,
                        "in_target": int(lane == target_lane), "iterations": result.iters, "stop_reason": result.reason,
                        "cost": result.J, "F_norm": result.F_norm, "b_min": result.b_min, "slack": result.slack,
                        "c_min": result.c_min, "braking_predicted": result.braking,
                        "braking_follower": result.follower_braking, "brake_max": braking, "fallback": result.fallback,
                        "zstep_stop": result.zstop, "step_ms": step_ms,
                        "d_min_m": float(np.min(np.hypot(*(z[1:, :2] - z[0, :2]).T)))})
    ep.states = np.array(ep.states)
    ep.controls = np.array(ep.controls).reshape(-1, 2)
    return ep
