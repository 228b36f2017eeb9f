"""The interactive strategy's closed-loop candidates (planner.strategy.Chase) one step on in a numba kernel: their
decisions were ~140 numpy calls on K-vectors a step, 50 steps per MPC step, so per-call overhead was most of the
interactive step's time; here one candidate at a time, with the same arithmetic in the same order (the same numbers).
The IDM following stays in Python (the world's own data.drivers.IDMDriver): few candidates follow at a step."""
import math

import numpy as np
from numba import njit


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
def chase_step(x, v, there, z, gaps, dv, lean_y, clearance, k, ahead, behind, v_unseen, lane_y, y_ref, stop_at, brake,
               tau, tau_x, align, dt, car_length, lane_width, near, v_stopped):
    """Chase's step for K candidates in states z (K, 4) from the predicted last step's x (K, SLOTS) m, v (K, SLOTS) m/s
    and target-lane cars `there` (K, SLOTS) bool; per candidate its gap (front, back slot) (K, 2), dv (NaN: it chases)
    m/s, lean_y m and clearance m; step k; where unseen cars may be ahead and behind at k = 0 (m) and their speed
    v_unseen m/s; stop_at (m), the point before which it can always stop braking at brake = -2 a_min (m/s^2). Returns
    a (K,) m/s^2 and y_t (K,) m before following, and who follows by IDM: follow (K,) bool, the bumper gap (K,) m to
    its leader (NaN: free road), the leader's v (K,) m/s and the cap (K,) m/s^2 on its acceleration (inf: none)."""
    K = len(z)
    a, y_t, follow = np.empty(K), np.empty(K), np.zeros(K, np.bool_)
    gap, v_lead, cap = np.full(K, np.nan), np.full(K, np.nan), np.full(K, np.inf)
    unseen_front, unseen_back = ahead + v_unseen * k * dt, behind + v_unseen * k * dt
    for b in range(K):
        x0, y0, v0, c = z[b, 0], z[b, 1], z[b, 3], clearance[b]
        lead = nearest(x, there, b, True)
        accept = math.isfinite(dv[b])  # the gap beside it now: the nearest predicted cars ahead and behind
        front = lead if accept else gaps[b, 0]
        back = nearest(x, there, b, False) if accept else gaps[b, 1]
        x_front = x[b, front] if front > 0 else unseen_front
        x_back = x[b, back] if back > 0 else unseen_back
        known = (front > 0) + (back > 0)
        v_gap = ((v[b, front] if front > 0 else 0.0) + (v[b, back] if back > 0 else 0.0)) / known if known else v0
        middle = 0.5 * (x_front + x_back)
        room = min(x_front - x0, x0 - x_back) - car_length
        stop = math.sqrt(brake * max(0.0, stop_at - (x0 + v0 * dt)))  # a step on: it brakes before it has passed the point
        if accept:
            v_sum, n_near = 0.0, 0
            for i in range(x.shape[1]):
                if there[b, i] and abs(x[b, i] - x[b, 0]) < near:
                    v_sum, n_near = v_sum + v[b, i], n_near + 1
            v_aim = max(0.0, (v_sum / n_near if n_near else v_unseen) + dv[b])
        else:
            v_aim = v_gap + (middle - x0) / tau_x
        a[b] = min((v_aim - v0) / tau, (stop - v0) / dt)
        room_front = x_front - x0 - car_length
        stopped = back > 0 and v[b, back] <= v_stopped
        enter = room_front >= c and (room >= c or stopped) if accept else room >= c
        y_t[b] = y_ref if enter else lean_y[b] if accept or abs(middle - x0) <= align else lane_y
        if accept and enter:  # turning in, from a standstill too: it follows the gap's front car
            follow[b], gap[b], cap[b] = True, room_front, (stop - v0) / dt
            v_lead[b] = v[b, front] if front > 0 else v_unseen
        if abs(y0 - y_ref) < lane_width / 4:  # in: it follows the car ahead
            follow[b], y_t[b], cap[b] = True, y_ref, np.inf
            gap[b], v_lead[b] = (x[b, lead] - x[b, 0] - car_length, v[b, lead]) if lead else (np.nan, np.nan)
    return a, y_t, follow, gap, v_lead, cap
