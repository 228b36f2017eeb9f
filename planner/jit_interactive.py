"""mpc=interactive's candidate search (planner.strategy.Interactive) compiled for the predictors the compiled core runs
itself (cv and the student: planner.jit_rollout.compiled_params): the open-loop candidates' bicycle rollouts (`track`,
planner.jit_bicycle), every candidate's predicted rollout with its plan fixed (`open_loop`) or answering the predictor step by
step (`chase`: strategy.Chase against the predictor's recursion), and the verdicts on them (`verdicts`), each one numba
call. In Python these were ~2,000 numpy calls on arrays of tens of elements a step, most of the interactive step's time.
The student runs once per distinct window (`alike`): the candidates share most of theirs.

planner.strategy's numpy code stays the reference and serves every other source. The arithmetic is the same, in the same
order, but numba's libm arctan, tan, tanh, pow and erf differ from numpy's SIMD loops and scipy's erf in the last bit
for some arguments, and the costs J and the student's layers sum in another order: the numbers agree to rounding
(plans to 1e-15, the student's 25- and 50-step rollouts to 1e-11 m on the bench's states), not bit for bit; the
candidates' names and order are the reference's (tests/test_interactive.py)."""
import math

import numpy as np
from numba import njit

from data.drivers import idm
from planner.jit_bicycle import advance
from planner.jit_chase import chase_step
from planner.jit_linalg import rmatvec


@njit(cache=True)
def drive(z, y_target, a, car):
    """strategy.drive for one ego in state z (4,) (x, y m, psi rad, v m/s), steering to y_target (m), accelerating at a
    (m/s^2): its controls delta (rad), a (m/s^2), and its next state, written into z; car = (l_f, l_r, dt, psi_lo,
    psi_hi, delta_lo, delta_hi, a_lo, a_hi, k_y, k_psi): the bicycle's geometry (m), step (s), the boxes and the lateral
    and heading gains (1/s)."""
    l_f, l_r, dt, psi_lo, psi_hi, d_lo, d_hi, a_lo, a_hi, k_y, k_psi = car
    y, psi, v = z[1], z[2], z[3]
    v_1 = max(v, 1.0)  # steering gains as at 1 m/s below it
    psi_d = min(max(math.atan(k_y * (y_target - y) / v_1), psi_lo), psi_hi)
    d = min(max((l_f + l_r) * k_psi * (psi_d - psi) / v_1, d_lo), d_hi)
    a = max(min(max(a, a_lo), a_hi), -v / dt)
    advance(z, d, a, l_f, l_r, dt)
    return d, a


@njit(cache=True)
def track(z0, y_target, v_target, x_target, tau, tau_x, car):
    """strategy.track: controls Delta, alpha (K, H) and states Z (K, 4H) of K candidates from z0 (4,) steering to
    y_target (K, H) m while their speed approaches v_target (K, H) m/s with time constant tau (s), closing on x_target
    (K, H) m with time constant tau_x (s) where it is not NaN."""
    K, H = y_target.shape
    Delta, alpha, Z = np.empty((K, H)), np.empty((K, H)), np.empty((K, 4 * H))
    for k in range(K):
        z = z0.copy()
        for t in range(H):
            closing = 0.0 if math.isnan(x_target[k, t]) else (x_target[k, t] - z[0]) / tau_x
            v_aim = max(0.0, v_target[k, t] + closing)
            Delta[k, t], alpha[k, t] = drive(z, y_target[k, t], (v_aim - z[3]) / tau, car)
            Z[k, 4 * t:4 * t + 4] = z
    return Delta, alpha, Z


@njit(cache=True)
def tracks(history, K, H):
    """K rollouts' tracks (K, T_obs + H, SLOTS, 2) in m: the observed history (T_obs, SLOTS, 2), then room for H
    predicted steps. A rollout's window at step t is its track's rows t..t + T_obs - 1: nothing is shifted (numba's
    strided slice copies cost more than the predictor)."""
    out = np.empty((K, history.shape[0] + H, history.shape[1], 2))
    for k in range(K):
        out[k, :history.shape[0]] = history
    return out


@njit(cache=True)
def alike(rep, track, row):
    """Refine rep (K,), each track's first track whose ego has driven the same path so far, by the ego's xy (m) just
    written into row `row` of the tracks (K, T_obs + H, SLOTS, 2): the tracks of one path have the same windows, so the
    predictor runs once for them (open-loop plans share the lean's prefix, chasing ones drive alike until one enters)."""
    old = rep.copy()
    for b in range(len(rep)):
        for c in range(old[b], b + 1):  # the first of b's old class with b's new xy: itself at the latest
            if old[c] == old[b] and track[c, row, 0, 0] == track[b, row, 0, 0] and track[c, row, 0, 1] == track[b, row, 0, 1]:
                rep[b] = c
                break


@njit(cache=True)
def predict_step(Wt, bs, s, track, new, T_obs, rep):
    """Write the predictor's next xy (m) of every other car into row `new` of each track (K, T_obs + H, SLOTS, 2), from
    the window of the T_obs rows before it: constant velocity where s is empty, else the student from its float64
    weights (student_head: Wt, bs) once per distinct window, those of the tracks that are their own rep (alike)."""
    K, M = track.shape[0], track.shape[2]
    for b in range(K):
        for m in range(1, M):
            for c in range(2):
                track[b, new, m, c] = 2.0 * track[b, new - 1, m, c] - track[b, new - 2, m, c]
    if len(s) == 0:
        return
    head = np.empty((K, len(s)))
    for b in range(K):
        if rep[b] == b:
            head[b] = student_head(Wt, bs, track[b, new - T_obs:new].copy().reshape(-1))
    for b in range(K):
        for r in range(len(s)):
            track[b, new, 1 + r // 2, r % 2] += s[r] * head[rep[b], r]


@njit(cache=True)
def transposed(Ws):
    """The layers' weights W' (in, out), contiguous: student_head's products then run along their rows."""
    return [np.ascontiguousarray(W.T) for W in Ws]


@njit(cache=True)
def student_head(Wt, bs, window):
    """The student's bounded head tanh(W_L h) (2N,) of one flattened window (T_obs SLOTS 2,) in m, its values only
    (distill.student.phi_jac64), from its layers' transposed weights Wt (transposed) and biases bs: a window at a time,
    so its numbers never depend on which others are predicted beside it (BLAS's do on the batch's size), and two
    candidates that tie stay tied."""
    h = window
    for k in range(len(Wt) - 1):
        a = rmatvec(Wt[k], h) + bs[k]
        for j in range(len(a)):
            a[j] = a[j] * (0.5 * (1.0 + math.erf(a[j] / math.sqrt(2.0))))  # exact GELU
        h = a
    return np.tanh(rmatvec(Wt[-1], h) + bs[-1])


@njit(cache=True)
def open_loop(Ws, bs, s, history, ego):
    """Predicted xy (K, H, SLOTS, 2) in m of every slot under K fixed ego plans, the ego's xy (K, H, 2) at steps 1..H,
    from the observed history (T_obs, SLOTS, 2): core.rollout.rollout by predict_step's predictor."""
    K, H, T_obs = ego.shape[0], ego.shape[1], history.shape[0]
    track, rep, Wt = tracks(history, K, H), np.zeros(K, np.int64), transposed(Ws)  # every window the history at first
    for t in range(H):
        predict_step(Wt, bs, s, track, T_obs + t, T_obs, rep)
        for b in range(K):
            track[b, T_obs + t, 0, 0], track[b, T_obs + t, 0, 1] = ego[b, t, 0], ego[b, t, 1]
        if len(s):  # constant velocity costs less than finding the alike windows
            alike(rep, track, T_obs + t)
    return track[:, T_obs:].copy()


@njit(cache=True)
def lane_of(y, lane_width, lanes):
    """data.world.Road.lane_of for one lateral position y (m): the index of the nearest lane centre, as a float."""
    return min(max(np.rint(y / lane_width), 0.0), lanes - 1.0)


@njit(cache=True)
def target_lane(track, new, dt, lane_width, lanes, target):
    """strategy.target_lane of the windows that end before row `new` of the tracks (K, T_obs + H, SLOTS, 2): x (K,
    SLOTS) m, v (K, SLOTS) m/s at their last step, and whether each car is in lane `target` (of `lanes`, lane_width m
    wide; the ego's slot False)."""
    K, M = track.shape[0], track.shape[2]
    x, v, there = np.empty((K, M)), np.empty((K, M)), np.zeros((K, M), np.bool_)
    for b in range(K):
        for i in range(M):
            x[b, i] = track[b, new - 1, i, 0]
            v[b, i] = (x[b, i] - track[b, new - 2, i, 0]) / dt
            there[b, i] = i > 0 and lane_of(track[b, new - 1, i, 1], lane_width, lanes) == target
    return x, v, there


@njit(cache=True)
def chase(Ws, bs, s, history, z, gaps, dv, lean_y, clearance, T, chase_constants, lane, car, follow):
    """strategy.Chase's K candidates driven T steps against predict_step's predictor from the observed history (T_obs,
    SLOTS, 2), as Source.react(history, Chase(...), T, K) drives them: Delta, alpha (K, T), Z (K, 4T) and the predicted
    xy (K, T, SLOTS, 2). z (K, 4): the egos' states (not modified); gaps (K, 2), dv, lean_y, clearance (K,) and
    chase_constants: Chase's own (jit_chase.chase_step's scalars after k); lane = (dt s, lane_width m, lanes, the
    target lane); car: drive's; follow: the IDM parameters (v0, T, s0, a_max, b, delta) of the ego's car-following
    once in the target lane (Chase.FOLLOW)."""
    K, T_obs = len(gaps), history.shape[0]
    track, z, rep, Wt = tracks(history, K, T), z.copy(), np.zeros(K, np.int64), transposed(Ws)
    Delta, alpha, Z = np.empty((K, T)), np.empty((K, T)), np.empty((K, 4 * T))
    for k in range(T):
        x, v, there = target_lane(track, T_obs + k, *lane)
        a, y_t, following, gap, v_lead, cap = chase_step(x, v, there, z, gaps, dv, lean_y, clearance, k, *chase_constants)
        for b in range(K):
            if following[b]:
                a[b] = min(idm(z[b, 3], gap[b], v_lead[b], *follow), cap[b])
            Delta[b, k], alpha[b, k] = drive(z[b], y_t[b], a[b], car)
            Z[b, 4 * k:4 * k + 4] = z[b]
            track[b, T_obs + k, 0, 0], track[b, T_obs + k, 0, 1] = z[b, 0], z[b, 1]
        predict_step(Wt, bs, s, track, T_obs + k, T_obs, rep)
        if len(s):
            alike(rep, track, T_obs + k)
    return Delta, alpha, Z, track[:, T_obs:].copy()


@njit(cache=True)
def quadratic(P, q, r, x):
    """1/2 x'Px + q'x + r (planner.cost.Quadratic)."""
    out = 0.0
    for i in range(len(x)):
        Px = 0.0
        for j in range(len(x)):
            Px += P[i, j] * x[j]
        out += 0.5 * x[i] * Px + q[i] * x[i]
    return out + r


@njit(cache=True)
def power(x, q):
    """x^q for x >= 0: by multiplication for a small whole q (the superellipse's p / 2 = 3), as pow to an ulp or two at
    a twentieth of its cost (pow was most of a verdict's time), else by pow."""
    n = int(q)
    if n != q or not 0 < n <= 4:
        return x**q
    out = x
    for _ in range(n - 1):
        out *= x
    return out


@njit(cache=True)
def measure(sq0, sq1, R, stretch, p):
    """core.rollout.b_i's shape (R m, stretch, p) for squared gaps sq0 along and sq1 across the road (m^2) as a number that
    rises with b_i: b_i itself on the ellipse (p = 2), else S = |dx / (stretch R)|^p + |dy / R|^p (to_b turns it into
    b_i: one pow per least S, not per car and step)."""
    if p == 2.0:
        return sq0 / stretch**2 + sq1 - R**2
    return power(sq0 / (stretch * R) ** 2, p / 2) + power(sq1 / R**2, p / 2)


@njit(cache=True)
def to_b(least, R, p):
    """b_i (m^2) of measure's number `least`; inf stays inf."""
    return least if p == 2.0 or least == np.inf else R**2 * least ** (2 / p) - R**2


@njit(cache=True)
def b_min(values, R, stretch, p):
    """The least b_i (m^2) over every step and car of a rollout's values (H, SLOTS, 2): core.rollout.b_i's shape (R m,
    stretch, p), inf without cars. On the superellipse b_i = R^2 S^(2/p) - R^2 rises with S, so it is taken at the
    least S (measure, to_b)."""
    least = np.inf
    for t in range(values.shape[0]):
        for i in range(1, values.shape[1]):
            least = min(least, measure((values[t, 0, 0] - values[t, i, 0]) ** 2, (values[t, 0, 1] - values[t, i, 1]) ** 2,
                                       R, stretch, p))
    return to_b(least, R, p)


@njit(cache=True)
def room(values, Z, R, stretch, p, y_ref, lane_width, lanes, target, far):
    """Interactive.room of predicted values (K, H, SLOTS, 2) beside K candidates' paths Z (K, 4H): per candidate the
    most, over the steps, of the least b_i (m^2) between the ego put at its x on the target lane's centre y_ref and
    the cars in lane `target` (of `lanes`, lane_width m wide), a car elsewhere moved `far` m along the road; inf
    without cars."""
    K, H, M = values.shape[0], values.shape[1], values.shape[2]
    out = np.full(K, -np.inf)
    for k in range(K):
        for t in range(H):
            least = np.inf
            for i in range(1, M):
                x = values[k, t, i, 0] + (0.0 if lane_of(values[k, t, i, 1], lane_width, lanes) == target else far)
                least = min(least, measure((Z[k, 4 * t] - x) ** 2, (y_ref - values[k, t, i, 1]) ** 2, R, stretch, p))
            out[k] = max(out[k], to_b(least, R, p))
    return out


@njit(cache=True)
def braking(values, history, dt):
    """The hardest braking (m/s^2, >= 0) of another car along the road over a rollout's values (H, SLOTS, 2), the last
    two observed steps of history (T_obs, SLOTS, 2) first (core.rollout.accelerations)."""
    least = 0.0
    for i in range(1, values.shape[1]):
        x_2, x_1 = history[-2, i, 0], history[-1, i, 0]
        for t in range(values.shape[0]):
            x = values[t, i, 0]
            least = min(least, (x - 2.0 * x_1 + x_2) / dt**2)
            x_2, x_1 = x_1, x
    return max(0.0, -least)


@njit(cache=True)
def verdicts(values, history, Delta, alpha, Z, shape, road, costs, T_p):
    """Interactive.verdicts of the predicted values (K, H, SLOTS, 2) on K candidates (Delta, alpha (K, H), Z (K, 4H)):
    b_min (K,) m^2, braking (K,) m/s^2, merge (K,) steps, J (K,) over T_p and overrun (K,) m. shape = (R m, stretch,
    p, dt s); road = (y_ref m, merge_tol m, brake = -2 a_min m/s^2, lane_end m, never: the merge step of no merge);
    costs: (P, q, r) of Phi_1, Phi_2, Phi_3 (planner.mpc.costs)."""
    R, stretch, p, dt = shape
    y_ref, merge_tol, brake, lane_end, never = road
    (P1, q1, r1), (P2, q2, r2), (P3, q3, r3) = costs
    K, H = Delta.shape
    b, braked, merge = np.empty(K), np.empty(K), np.full(K, never, np.int64)
    J, overrun = np.empty(K), np.zeros(K)
    for k in range(K):
        b[k], braked[k] = b_min(values[k], R, stretch, p), braking(values[k], history, dt)
        for t in range(H):
            if abs(Z[k, 4 * t + 1] - y_ref) <= merge_tol:  # as the episode counts it: astride the line is not in
                merge[k] = t + 1
                break
            reach = Z[k, 4 * t] + Z[k, 4 * t + 3] ** 2 / brake - lane_end
            overrun[k] = max(overrun[k], reach)
        J[k] = (quadratic(P1, q1, r1, Delta[k, :T_p]) + quadratic(P2, q2, r2, alpha[k, :T_p])
                + quadratic(P3, q3, r3, Z[k, :4 * T_p]))
    return b, braked, merge, J, overrun
