"""Closed loop: plan, apply the first control to the nonlinear bicycle, let the others move, observe; record every step.

The others move by the world's own reactive drivers (`world=reactive`) or by the predictor (`world=predictor`, as in
the paper). Before t = 0 nothing was observed: the first T_obs history steps are back-filled by driving every car
backwards at its initial heading and speed (constant velocity).
"""
import time
from dataclasses import dataclass, field

import numpy as np

from data import bicycle
from data.world import World, overlap


def backfill(z, T_obs, dt):
    """History (T_obs, SLOTS, 2) ending at the current xy of states z (M, 4), earlier steps at constant velocity."""
    heading = np.stack([np.cos(z[:, 2]), np.sin(z[:, 2])], -1)
    return np.stack([z[:, :2] - k * dt * z[:, 3:4] * heading for k in range(T_obs - 1, -1, -1)])


def predictor_move(world: World, history, ego_u, source):
    """Advance dt with the ego on the bicycle and every other car where the predictor puts it; returns collided pairs."""
    p = world.params
    nxt = source.values(history, np.zeros((1, 1, 2)))[0, 0]  # one step; the ego slot is overwritten below
    z = world.z.copy()
    moved = nxt[1:] - z[1:, :2]
    z[1:, 2] = np.where(np.hypot(*moved.T) > 1e-6, np.arctan2(moved[:, 1], moved[:, 0]), z[1:, 2])
    z[1:, 3] = np.hypot(*moved.T) / p.dt
    z[1:, :2] = nxt[1:]
    z[0] = bicycle.step(world.z[0], ego_u, p)
    world.z, world.t = z, world.t + p.dt
    hits = [(i, j) for i in range(len(z)) for j in range(i + 1, len(z)) if overlap(z[i], z[j], world.road)]
    world.collisions += [(world.t, i, j) for i, j in hits]
    return hits


@dataclass
class Episode:
    """A driven episode: states (T+1, M, 4), applied controls (T, 2), one record per MPC step, notes."""

    states: list = field(default_factory=list)
    controls: list = field(default_factory=list)
    rows: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    collided: bool = False


def drive(world: World, planner, source, x_ref, target_lane, T_obs, max_steps, others):
    """Run planner(obs, warm) -> StepResult until the ego passes x_ref or max_steps; never raises for a bad step.

    T_obs: observed steps; others: "reactive" (the world's drivers) or "predictor" (moved by `source`)."""
    from planner.mpc import Observation

    sees_world = hasattr(source.predictor, "world")  # gradients=oracle: the world itself, a diagnostic ceiling
    ep = Episode(states=[world.z.copy()])
    history = backfill(world.z, T_obs, world.params.dt)
    start_hits = [j for j in range(1, len(world.z)) if overlap(world.z[0], world.z[j], world.road)]
    if start_hits:
        ep.notes.append(f"start in collision with car(s) {start_hits}")
        ep.collided = True
    u_prev, warm = np.zeros(2), None
    for k in range(max_steps):
        if world.z[0, 0] >= x_ref:
            break
        obs = Observation(world.z[0].copy(), u_prev.copy(), history.copy())
        if sees_world:
            source.predictor.world = world
        t0 = time.perf_counter()
        result = planner(obs, warm)
        step_ms = 1e3 * (time.perf_counter() - t0)
        u = np.nan_to_num(result.u)
        hits = world.step(u) if others == "reactive" else predictor_move(world, history, u, source)
        if any(0 in pair for pair in hits):
            ep.collided = True
        history = np.concatenate([history[1:], world.z[None, :, :2]])
        u_prev, warm = u, result.plan
        ep.states.append(world.z.copy())
        ep.controls.append(u)
        lane = int(world.road.lane_of(world.z[0, 1]))
        ep.rows.append({"step": k + 1, "time_s": round(world.t, 6), "x": world.z[0, 0], "y": world.z[0, 1],
                        "psi": world.z[0, 2], "v": world.z[0, 3], "delta": u[0], "a": u[1], "lane": lane,
                        "in_target": int(lane == target_lane), "iterations": result.iters, "stop_reason": result.reason,
                        "cost": result.J, "F_norm": result.F_norm, "b_min": result.b_min, "slack": result.slack,
                        "fallback": result.fallback, "zstep_stop": result.zstop, "step_ms": step_ms,
                        "d_min_m": float(np.min(np.hypot(*(world.z[1:, :2] - world.z[0, :2]).T)))})
    ep.states = np.array(ep.states)
    ep.controls = np.array(ep.controls).reshape(-1, 2)
    return ep
