"""The interactive strategy's closed-loop candidates (planner.strategy.Chase) one step on in numba kernels, one candidate
at a time: their decisions were ~140 numpy calls on K-vectors a step, 50 steps per MPC step, so per-call overhead was most
of the interactive step's time. The same kernels move them against any predictor: a Python one's recursion calls
`move` once a step (Source.react), a compiled one's runs inside planner.jit_interactive.chase."""
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from data.drivers import idm
from planner.jit_bicycle import Car, drive


class Gaps(NamedTuple):
    """K chasing candidates as the kernels read them (strategy.Chase builds it): per candidate its gap's (front, back)
    slots (K, 2; 0: none seen), dv (K,) m/s (NaN: it chases its gap, else it accepts the gap beside it at the nearby
    stream's speed plus dv), lean_y (K,) m and clearance (K,) m; where unseen target-lane cars may be ahead and behind
    at step 0 (m) and their speed v_unseen (m/s); the current lane's centre lane_y and the target lane's y_ref (m);
    stop_at (m), the point before which a candidate can always stop braking at brake = -2 a_min (m/s^2); the time
    constants tau, tau_x (s); align (m); the road's dt (s), car_length, lane_width (m), lanes and target lane index;
    near (m) and v_stopped (m/s) of the gap acceptance; the car as drive moves it and the IDM parameters (v0, T, s0,
    a_max, b, delta) it follows with once in the target lane."""

    gaps: np.ndarray
    dv: np.ndarray
    lean_y: np.ndarray
    clearance: np.ndarray
    ahead: float
    behind: float
    v_unseen: float
    lane_y: float
    y_ref: float
    stop_at: float
    brake: float
    tau: float
    tau_x: float
    align: float
    dt: float
    car_length: float
    lane_width: float
    lanes: float
    target: float
    near: float
    v_stopped: float
    car: Car
    follow: tuple


@njit(cache=True)
def lane_of(y, lane_width, lanes):
    """data.world.Road.lane_of for one lateral position y (m): the index of the nearest lane centre, as a float."""
    return min(max(np.rint(y / lane_width), 0.0), lanes - 1.0)


@njit(cache=True)
def target_lane(track, new, g):
    """strategy.target_lane of the windows that end before row `new` of the tracks (K, rows, SLOTS, 2): x (K, SLOTS) m,
    v (K, SLOTS) m/s at their last step, and whether each car is in the Gaps g's target lane (the ego's slot False)."""
    K, M = track.shape[0], track.shape[2]
    x, v, there = np.empty((K, M)), np.empty((K, M)), np.zeros((K, M), np.bool_)
    for b in range(K):
        for i in range(M):
            x[b, i] = track[b, new - 1, i, 0]
            v[b, i] = (x[b, i] - track[b, new - 2, i, 0]) / g.dt
            there[b, i] = i > 0 and lane_of(track[b, new - 1, i, 1], g.lane_width, g.lanes) == g.target
    return x, v, there


@njit(cache=True)
def nearest(x, there, b, ahead):
    """The slot of the car of row b of `there` (K, SLOTS) bool nearest ahead of (behind: at or behind) the ego's x, slot
    0 of row b of x (K, SLOTS) m; 0 where there is none; ties to the lowest slot."""
    best, x0 = 0, x[b, 0]
    for i in range(1, x.shape[1]):
        if there[b, i] and ((x[b, i] > x0 and (best == 0 or x[b, i] < x[b, best])) if ahead else
                            (x[b, i] <= x0 and (best == 0 or x[b, i] > x[b, best]))):
            best = i
    return best


@njit(cache=True)
def decide(x, v, there, z, g, b, k):
    """Chase's decision for candidate b in state z (4,) at step k from the predicted last step's x (K, SLOTS) m, v (K,
    SLOTS) m/s and target-lane cars `there` (K, SLOTS) bool: its acceleration (m/s^2) and lateral target y (m)."""
    x0, y0, v0, c = z[0], z[1], z[3], g.clearance[b]
    lead = nearest(x, there, b, True)
    accept = math.isfinite(g.dv[b])  # the gap beside it now: the nearest predicted cars ahead and behind
    front = lead if accept else g.gaps[b, 0]
    back = nearest(x, there, b, False) if accept else g.gaps[b, 1]
    x_front = x[b, front] if front > 0 else g.ahead + g.v_unseen * k * g.dt
    x_back = x[b, back] if back > 0 else g.behind + g.v_unseen * k * g.dt
    known = (front > 0) + (back > 0)
    v_gap = ((v[b, front] if front > 0 else 0.0) + (v[b, back] if back > 0 else 0.0)) / known if known else v0
    middle = 0.5 * (x_front + x_back)
    room = min(x_front - x0, x0 - x_back) - g.car_length
    stop = math.sqrt(g.brake * max(0.0, g.stop_at - (x0 + v0 * g.dt)))  # a step on: it brakes before it has passed the point
    if accept:
        v_sum, n_near = 0.0, 0
        for i in range(x.shape[1]):
            if there[b, i] and abs(x[b, i] - x[b, 0]) < g.near:
                v_sum, n_near = v_sum + v[b, i], n_near + 1
        v_aim = max(0.0, (v_sum / n_near if n_near else g.v_unseen) + g.dv[b])
    else:
        v_aim = v_gap + (middle - x0) / g.tau_x
    a = min((v_aim - v0) / g.tau, (stop - v0) / g.dt)
    room_front = x_front - x0 - g.car_length
    stopped = back > 0 and v[b, back] <= g.v_stopped
    enter = room_front >= c and (room >= c or stopped) if accept else room >= c
    y_t = g.y_ref if enter else g.lean_y[b] if accept or abs(middle - x0) <= g.align else g.lane_y
    if abs(y0 - g.y_ref) < g.lane_width / 4:  # in: it follows the car ahead
        gap, v_lead = (x[b, lead] - x[b, 0] - g.car_length, v[b, lead]) if lead else (np.nan, np.nan)
        return idm(v0, gap, v_lead, *g.follow), g.y_ref
    if accept and enter:  # turning in, from a standstill too: it follows the gap's front car
        return min(idm(v0, room_front, v[b, front] if front > 0 else g.v_unseen, *g.follow), (stop - v0) / g.dt), y_t
    return a, y_t


@njit(cache=True)
def move(track, new, z, g, k, Delta, alpha, Z):
    """The K candidates of Gaps g in states z (K, 4) one step on (step k), written into z and into Delta, alpha (K, T) and
    Z (K, 4T) at k, from the predicted windows that end before row `new` of the tracks (K, rows, SLOTS, 2)."""
    x, v, there = target_lane(track, new, g)
    for b in range(len(z)):
        a, y_t = decide(x, v, there, z[b], g, b, k)
        Delta[b, k], alpha[b, k] = drive(z[b], y_t, a, g.car)
        Z[b, 4 * k:4 * k + 4] = z[b]
