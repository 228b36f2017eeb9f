"""mpc=interactive's candidate search (planner.strategy.Interactive) in numba kernels, one call each, for every source:
the open-loop candidates' bicycle rollouts (`track`), the verdicts on any predicted rollout (`verdicts`, `room`,
`foreseen`: a Judge of named settings), and, for the predictors written as kernels (cv and the student:
planner.jit_rollout.values_params), every candidate's predicted rollout with its plan fixed (`open_loop`) or answering
the predictor step by step (`chase`: strategy.Chase's kernels inside the predictor's recursion); other predictors roll
out in Python (planner.gradients.Source), Chase moving by the same kernels. In numpy these were ~2,000 calls on arrays
of tens of elements a step, most of the interactive step's time. The student runs once per distinct window (`alike`):
the candidates share most of theirs."""
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from distill import student
from planner.jit_bicycle import drive
from planner.jit_chase import lane_of, move


class Judge(NamedTuple):
    """What the verdicts read (Interactive.judge_of builds it): the safety shape's R (m), stretch and p, dt (s), the
    target lane's y_ref (m), merge_tol (m), brake = -2 a_min (m/s^2), lane_end (m), never (the merge step of no merge),
    the road's lane_width (m), lanes and target lane index, and far (m: a car outside the target lane moved this far
    leaves the room there)."""

    R: float
    stretch: float
    p: float
    dt: float
    y_ref: float
    merge_tol: float
    brake: float
    lane_end: float
    never: int
    lane_width: float
    lanes: float
    target: float
    far: float


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
def predict_step(Ws, bs, s, track, new, T_obs, rep):
    """Write the predictor's next xy (m) of every other car into row `new` of each track (K, T_obs + H, SLOTS, 2), from
    the window of the T_obs rows before it: constant velocity where s is empty, else the student from its float64
    weights (distill.student.head) once per distinct window, those of the tracks that are their own rep (alike)."""
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
            head[b] = student.head(Ws, bs, track[b, new - T_obs:new].copy().reshape(-1), False)[0]
    for b in range(K):
        for r in range(len(s)):
            track[b, new, 1 + r // 2, r % 2] += s[r] * head[rep[b], r]


@njit(cache=True)
def open_loop(Ws, bs, s, history, ego):
    """Predicted xy (K, H, SLOTS, 2) in m of every slot under K fixed ego plans, the ego's xy (K, H, 2) at steps 1..H,
    from the observed history (T_obs, SLOTS, 2): core.rollout.rollout by predict_step's predictor."""
    K, H, T_obs = ego.shape[0], ego.shape[1], history.shape[0]
    track, rep = tracks(history, K, H), np.zeros(K, np.int64)  # every window the history at first
    for t in range(H):
        predict_step(Ws, bs, s, track, T_obs + t, T_obs, rep)
        for b in range(K):
            track[b, T_obs + t, 0, 0], track[b, T_obs + t, 0, 1] = ego[b, t, 0], ego[b, t, 1]
        if len(s):  # constant velocity costs less than finding the alike windows
            alike(rep, track, T_obs + t)
    return track[:, T_obs:].copy()


@njit(cache=True)
def chase(Ws, bs, s, history, z, g, T):
    """strategy.Chase's K candidates (their Gaps g, states z (K, 4), not modified) driven T steps against
    predict_step's predictor from the observed history (T_obs, SLOTS, 2), as Source.react(history, Chase(...), T, K)
    drives them: Delta, alpha (K, T), Z (K, 4T) and the predicted xy (K, T, SLOTS, 2)."""
    K, T_obs = len(z), history.shape[0]
    track, z, rep = tracks(history, K, T), z.copy(), np.zeros(K, np.int64)
    Delta, alpha, Z = np.empty((K, T)), np.empty((K, T)), np.empty((K, 4 * T))
    for k in range(T):
        move(track, T_obs + k, z, g, k, Delta, alpha, Z)
        for b in range(K):
            track[b, T_obs + k, 0, 0], track[b, T_obs + k, 0, 1] = z[b, 0], z[b, 1]
        predict_step(Ws, bs, s, track, T_obs + k, T_obs, rep)
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
def room(values, Z, j):
    """Interactive's room of predicted values (K, H, SLOTS, 2) beside K candidates' paths Z (K, 4H): per candidate the
    most, over the steps, of the least b_i (m^2) between the ego put at its x on the target lane's centre y_ref and
    the cars in the target lane, a car elsewhere moved `far` m along the road (Judge j); inf without cars."""
    K, H, M = values.shape[0], values.shape[1], values.shape[2]
    out = np.full(K, -np.inf)
    for k in range(K):
        for t in range(H):
            least = np.inf
            for i in range(1, M):
                x = values[k, t, i, 0] + (0.0 if lane_of(values[k, t, i, 1], j.lane_width, j.lanes) == j.target else j.far)
                least = min(least, measure((Z[k, 4 * t] - x) ** 2, (j.y_ref - values[k, t, i, 1]) ** 2, j.R, j.stretch, j.p))
            out[k] = max(out[k], to_b(least, j.R, j.p))
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
def foreseen(values, history, j):
    """What a verdict takes from the predictor's values (K, H, SLOTS, 2) after the observed history (T_obs, SLOTS, 2):
    min b_i (K,) m^2 and the hardest braking imposed on another car (K,) m/s^2 (Judge j)."""
    K = len(values)
    b, braked = np.empty(K), np.empty(K)
    for k in range(K):
        b[k], braked[k] = b_min(values[k], j.R, j.stretch, j.p), braking(values[k], history, j.dt)
    return b, braked


@njit(cache=True)
def verdicts(values, history, Delta, alpha, Z, j, costs, T_p):
    """Interactive's verdicts of the predicted values (K, H, SLOTS, 2) on K candidates (Delta, alpha (K, H), Z (K,
    4H)) by the Judge j: b_min (K,) m^2, braking (K,) m/s^2, merge (K,) steps, J (K,) over T_p and overrun (K,) m;
    costs: (P, q, r) of Phi_1, Phi_2, Phi_3 (planner.mpc.costs)."""
    (P1, q1, r1), (P2, q2, r2), (P3, q3, r3) = costs
    K, H = Delta.shape
    b, braked = foreseen(values, history, j)
    merge, J, overrun = np.full(K, j.never, np.int64), np.empty(K), np.zeros(K)
    for k in range(K):
        for t in range(H):
            if abs(Z[k, 4 * t + 1] - j.y_ref) <= j.merge_tol:  # as the episode counts it: astride the line is not in
                merge[k] = t + 1
                break
            reach = Z[k, 4 * t] + Z[k, 4 * t + 3] ** 2 / j.brake - j.lane_end
            overrun[k] = max(overrun[k], reach)
        J[k] = (quadratic(P1, q1, r1, Delta[k, :T_p]) + quadratic(P2, q2, r2, alpha[k, :T_p])
                + quadratic(P3, q3, r3, Z[k, :4 * T_p]))
    return b, braked, merge, J, overrun
