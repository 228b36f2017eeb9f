"""One receding-horizon step: build the MPC about the observation, warm-start from the shifted plan, solve, fall back.

A step never raises for a bad observation, a solver failure, any other error in building or solving it, or an unsafe
result: it returns the shifted previous plan (if the predictor still finds it safe) or braking in lane, with the reason.
"""
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from scipy import linalg

from core.jobs import UserError
from core.rollout import accelerations, b_i, ego_xy
from data import bicycle
from data.drivers import IDMDriver
from data.world import Road, steer_to
from planner import admm, cost, dynamics, jit_admm, jit_rollout, jit_zstep, repair
from planner.jit_zstep import CompiledSafety
from planner.qp import SolverFailure
from planner.safety import Safety


@dataclass(frozen=True)
class KeepAhead:
    """When the nearest target-lane car behind the ego (within `near` m) is seen slowing for it, the lean starts aim at
    that car's speed plus dv instead of their own v, so a driver who yields to the nudge is not overtaken by it (SI)."""

    near: float  # m: how far behind the ego's centre that car's centre may be
    dv: float  # m/s: kept above its speed
    slowing: float  # m/s^2: it counts as slowing once it decelerates harder than this over the last observed steps
    slower: float  # m/s: ... or drives this much slower than the target-lane car ahead of the ego


@dataclass(frozen=True)
class Settings:
    """Everything a step needs besides the observation and the Z-step, SI units, data only; built from the `planner`
    config's `mpc` node, whose YAML is the one home of every value (planner.setup passes the scenario's y_ref, v_ref, road
    and params)."""

    name: str  # the conf/mpc/ option (MLflow param `mpc`): paper | courteous
    weights: cost.Weights
    y_ref: float  # m
    v_ref: float  # m/s
    road: Road
    params: bicycle.BicycleParams
    T_p: int  # prediction horizon (steps of dt)
    rho: float  # ADMM penalty
    r: float  # ego's safety radius (m)
    r_i: float  # the others' safety radius (m)
    eps: float  # safety margin (m)
    stretch: float  # the safety ellipse's along-road semi-axis over R (core.rollout.b_i); 1: the paper's circle
    shape: float  # the exponent p of the safety shape (core.rollout.b_i): 2 the ellipse, higher a rounded rectangle
    b_courtesy: float | None  # courtesy rows: nobody predicted to brake harder than this (m/s^2); None: none (the paper)
    delta_box: tuple  # rad
    a_box: tuple  # m/s^2
    psi_box: tuple  # rad
    v_box: tuple  # m/s
    y_margin: float  # how far the ego's centre may leave the outer lane centres (m)
    linearize: str  # last_observed | along_plan
    core: str  # compiled (numba kernels, DAQP) | reference (numpy, OSQP)
    admm: admm.ADMMSettings  # planner.admm.admm_solve's max_iters, tol_F, tol_step
    osqp: dict  # OSQP settings of every sub-problem
    check_tol: float  # b_i violation (m^2) tolerated in the plan and in the nonlinear rollout of its controls
    check_steps: int  # steps of that rollout checked: only its start is ever applied, the rest is replanned
    check_relative: bool  # also accept a plan no less safe than braking in lane (see acceptable)
    repair_iters: int  # repair steps (planner.repair) for a plan that fails the check; 0: none, the paper
    repair_margin: float  # b_i (m^2) a repair step aims for on the linearised rollout
    brake: float  # deceleration of the braking-in-lane fallback (m/s^2)
    starts: tuple  # extra ADMM solves [offset (m), a (m/s^2), v (m/s) or None: v_ref], aiming off the target lane (lane_starts); (): none
    progress: float  # m: a plan that ends this much nearer y_ref than the ego is now, or in the target lane, merges (choose)
    follower: IDMDriver | None  # the nominal driver by whom choose judges the braking a plan imposes; None: none (the paper)
    keep_ahead: KeepAhead | None  # lean starts that follow a yielding driver through (lane_starts); None: their own v

    @property
    def R(self) -> float:
        """Single-circle safety distance r + r_i + eps (m), eq. (6)."""
        return self.r + self.r_i + self.eps


class Observation(NamedTuple):
    """What the planner sees: ego state z0 = [x, y, psi, v], last applied (delta, a), xy history (T_obs, SLOTS, 2)."""

    z0: np.ndarray
    u_prev: np.ndarray
    history: np.ndarray


class StepResult(NamedTuple):
    """The control to apply (delta rad, a m/s^2), the plan to warm-start from (None: start cold), and what happened."""

    u: np.ndarray
    plan: admm.ADMMState
    J: float
    iters: int
    reason: str
    F_norm: float
    b_min: float
    slack: float
    fallback: str  # "" when the solver's plan was applied
    zstop: str = ""  # why the last Z-update stopped, where its solver says (PyGranso's termination)
    c_min: float = np.nan  # the plan's smallest courtesy row a_i + b_c (m/s^2), where the Z-step has them
    braking: float = np.nan  # the hardest braking of another car (m/s^2) the predictor expects under the plan's rollout
    follower_braking: float = np.nan  # the hardest braking of the nominal follower (Settings.follower) behind the plan (m/s^2)


def simulate(z0, Delta, alpha, params):
    """Nonlinear bicycle rollout of the controls: Z (4T_p,) stacking z(1..T_p)."""
    z, out = np.asarray(z0, float), []
    for d, a in zip(Delta, alpha):
        z = bicycle.step(z, [d, a], params)
        out.append(z)
    return np.concatenate(out)


def shift(plan: admm.ADMMState):
    """The previous plan one step on: drop the first step, repeat the last (Z by its last state, mu by its last block)."""
    roll = lambda a, k: np.concatenate([a[k:], a[-k:]])
    return admm.ADMMState(roll(plan.Delta, 1), roll(plan.alpha, 1), roll(plan.Z, 4), roll(plan.mu, 4), plan.zstate)


def state_box(s: Settings):
    """z_min, z_max (4T_p,): x free, y within the road, psi and v boxed."""
    y_lo, y_hi = -s.y_margin, s.road.centre(s.road.lanes - 1) + s.y_margin
    lo = np.tile([-np.inf, y_lo, s.psi_box[0], s.v_box[0]], s.T_p)
    hi = np.tile([np.inf, y_hi, s.psi_box[1], s.v_box[1]], s.T_p)
    return lo, hi


def costs(s: Settings, u_prev):
    """Phi_1, Phi_2, Phi_3 for this step (the rate terms start from the last applied input)."""
    return (cost.Phi_1(s.T_p, s.weights, u_prev[0]), cost.Phi_2(s.T_p, s.weights, u_prev[1]),
            cost.Phi_3(s.T_p, s.weights, s.y_ref, s.v_ref))


def J_of(s: Settings, u_prev, Delta, alpha, Z):
    """The cost J of a plan."""
    Phi_1, Phi_2, Phi_3 = costs(s, u_prev)
    return Phi_1(Delta) + Phi_2(alpha) + Phi_3(Z)


def start_point(s: Settings, obs: Observation, warm: admm.ADMMState | None):
    """Where a step's solver starts (the shifted previous plan, or zero inputs rolled out: cold) and the dynamics
    linearised for it; shared by ADMM and solver=ipopt so both solve the same problem from the same point."""
    z0 = np.asarray(obs.z0, float)
    if warm is None:
        Delta, alpha = np.zeros(s.T_p), np.zeros(s.T_p)
        start = admm.ADMMState(Delta, alpha, simulate(z0, Delta, alpha, s.params), np.zeros(4 * s.T_p))
    else:
        start = shift(warm)._replace(zstate=None)
    return start, linearization(s, obs, start)


def linearization(s: Settings, obs: Observation, start: admm.ADMMState):
    """Eq. (5)'s dynamics for a solve from `start`: about the last observed state, or along the start's plan."""
    plan = (start.Delta, start.alpha, start.Z) if s.linearize == "along_plan" else None
    return dynamics.linearize(np.asarray(obs.z0, float), obs.u_prev[0], obs.u_prev[1], s.params, s.T_p, plan)


def yielding_speed(s: Settings, history):
    """The speed (m/s) of the nearest target-lane car behind the ego, within s.keep_ahead.near, when the observed history
    (T_obs, SLOTS, 2) shows it slowing for the ego (see KeepAhead); None when there is none, or it is not slowing."""
    if len(history) < 3:  # no acceleration to read
        return None
    k, dt = s.keep_ahead, s.params.dt
    x, y = history[-1, :, 0], history[-1, :, 1]
    v = (history[-1, :, 0] - history[-2, :, 0]) / dt
    in_target = s.road.lane_of(y) == s.road.lane_of(s.y_ref)
    in_target[0] = False
    behind = np.flatnonzero(in_target & (x <= x[0]) & (x >= x[0] - k.near))
    if len(behind) == 0:
        return None
    b = behind[np.argmax(x[behind])]
    decel = -(history[-1, b, 0] - 2 * history[-2, b, 0] + history[-3, b, 0]) / dt**2
    ahead = np.flatnonzero(in_target & (x > x[0]))
    lag = v[ahead[np.argmin(x[ahead])]] - v[b] if len(ahead) else 0.0
    return float(v[b]) if decel > k.slowing or lag > k.slower else None


def lane_starts(s: Settings, obs: Observation):
    """The extra ADMM solves (name, start, settings): for each [offset (m), a (m/s^2), v (m/s)] in s.starts, ADMM aims at
    y_ref = the current lane's centre moved `offset` towards the scenario's y_ref (0: wait in lane; 1.9: lean in, the
    nudge) and at v_ref = v (None: the scenario's), starting from holding the lane at a (lane_plan); with s.keep_ahead a
    lean (offset > 0) beside a car seen yielding aims at that car's speed plus dv instead, to take the room it opens
    (stopped, the ego would let it pass). The target lane's pull would draw every start into the same basin; these
    solves stay in theirs (choose)."""
    out, lane_y = [], s.road.centre(s.road.lane_of(obs.z0[1]))
    v_yield = yielding_speed(s, obs.history) if s.keep_ahead is not None else None
    for offset, a, v in s.starts:
        y, v = lane_y + float(offset) * np.sign(s.y_ref - lane_y), s.v_ref if v is None else float(v)
        if offset > 0 and v_yield is not None:
            v = float(np.clip(v_yield + s.keep_ahead.dv, *s.v_box))
        Delta, alpha = lane_plan(s, obs.z0, a)
        start = admm.ADMMState(Delta, alpha, simulate(obs.z0, Delta, alpha, s.params), np.zeros(4 * s.T_p))
        out.append((f"y {y:+.1f} m, v {v:.1f} m/s", start, replace(s, y_ref=y, v_ref=v)))
    return out


def courtesy(s: Settings):
    """The Safety's courtesy argument: (dt s, b_c m/s^2), or None without courtesy rows."""
    return None if s.b_courtesy is None else (s.params.dt, float(s.b_courtesy))


def build(s: Settings, obs: Observation, source, warm: admm.ADMMState | None, zstep, start: admm.ADMMState = None):
    """The step's Problem (eq. (5) by linearization), its Solvers (the Z-step built by `zstep`, a planner.zstep class
    with its settings bound) and the ADMM start, Z clipped to the state box: `start`, or start_point's from warm."""
    start = start_point(s, obs, warm)[0] if start is None else start
    lo, hi = state_box(s)
    prob = admm.Problem(linearization(s, obs, start), *costs(s, obs.u_prev), float(s.rho), tuple(s.delta_box),
                        tuple(s.a_box), lo, hi)
    if s.core == "compiled":
        safety = CompiledSafety(source, obs.history, s.R, s.T_p, courtesy(s), s.stretch, s.shape)
        solvers = admm.solvers(prob, jit_zstep.compiled(zstep), safety, s.osqp)
    else:
        solvers = admm.solvers(prob, zstep, Safety(source, obs.history, s.R, s.T_p, courtesy(s), s.stretch, s.shape), s.osqp)
    return prob, solvers, start._replace(Z=np.clip(start.Z, lo, hi))


def acceptable(s: Settings, obs: Observation, source, b_min: float) -> bool:
    """Whether a plan whose checked rollout has min b_i = b_min (m^2) may be applied: b_min >= -check_tol, or with
    check_relative no worse than braking in lane (its b_min, capped at 0, minus check_tol). Beside a car that stops to
    let a straddling ego in, every plan breaks b_i >= 0 for a while; judged against zero they all fail, and braking to a
    stop there waits for a car that waits for the ego."""
    if b_min >= -s.check_tol:
        return True
    return s.check_relative and b_min >= min(0.0, plan_safe(s, obs, source, *brake_plan(s, obs.z0))[0]) - s.check_tol


def rollout(s: Settings, obs: Observation, source, Delta, alpha):
    """The nonlinear rollout Z of (Delta, alpha) and the predictor's values (T_p, SLOTS, 2) under it."""
    Z = simulate(obs.z0, Delta, alpha, s.params)
    ego = ego_xy(Z, s.T_p)
    compiled = jit_rollout.compiled_jacobian(source) if s.core == "compiled" else None  # cv, student: values and J in ~0.1 ms
    return Z, compiled(obs.history, ego)[0] if compiled else source.values(obs.history, ego[None])[0]


def checked_b(s: Settings, values) -> float:
    """min b_i (m^2) over the first check_steps of a rollout's predictor values (T_p, SLOTS, 2)."""
    return float(b_i(values, s.R, s.stretch, s.shape)[:, :s.check_steps].min(initial=np.inf))


def plan_safe(s: Settings, obs: Observation, source, Delta, alpha):
    """min b_i (m^2) over the first check_steps of the nonlinear rollout of (Delta, alpha) against the predictor's reaction."""
    Z, values = rollout(s, obs, source, Delta, alpha)
    return checked_b(s, values), Z


def imposed(s: Settings, obs: Observation, values) -> float:
    """The hardest braking (m/s^2, >= 0) the predictor expects of another car, from its values (T_p, SLOTS, 2) over a
    plan's rollout."""
    return float(max(0.0, -accelerations(values, obs.history, s.params.dt).min(initial=0.0)))


def follower_braking(s: Settings, obs: Observation, Z, values) -> float:
    """The hardest braking (m/s^2, >= 0) that s.follower, an IDM driver, would need behind the ego's plan Z (4T_p,), for
    each other car behind the ego in the plan's lane at a step: there by the predictor's values (T_p, SLOTS, 2), or
    last seen there (the world has a car changing lanes follow the leaders of both); 0 without s.follower. Constant
    velocity predicts no braking; this judges the gap a plan leaves, whoever predicts the positions."""
    if s.follower is None:
        return 0.0
    ego = Z.reshape(-1, 4)
    x = np.concatenate([obs.history[-1:, 1:, 0], values[:, 1:, 0]])  # (T_p + 1, N), the last observed step first
    v = np.diff(x, axis=0) / s.params.dt  # (T_p, N): along the road, as IDM follows
    lane = s.road.lane_of(ego[:, 1])[:, None]
    there = (s.road.lane_of(values[:, 1:, 1]) == lane) | (s.road.lane_of(obs.history[-1, 1:, 1]) == lane)
    behind = there & (values[:, 1:, 0] < ego[:, :1])
    a = [s.follower.acceleration(v[k, i], ego[k, 0] - values[k, i + 1, 0] - s.road.car_length, ego[k, 3])
         for k, i in zip(*np.nonzero(behind))]
    return float(max(0.0, -min(a, default=0.0)))


def lane_plan(s: Settings, z0, a):
    """Controls Delta, alpha (T_p,) that steer to the current lane's centre (straddling: the lane away from y_ref) at
    acceleration a (m/s^2) within the box, never into reverse (the bicycle's v may go negative)."""
    z, Delta, alpha = np.asarray(z0, float), [], []
    lane_y = s.road.centre(s.road.lane_of(z[1]))
    if abs(z[1] - lane_y) > (s.road.lane_width - s.road.car_width) / 2:  # straddling: abort, back away from y_ref
        lane_y = s.road.centre(s.road.lane_of(z[1] - np.sign(s.y_ref - z[1]) * s.road.lane_width / 2))
    for _ in range(s.T_p):
        Delta.append(float(np.clip(steer_to(z, lane_y, s.params), *s.delta_box)))
        alpha.append(max(float(np.clip(a, *s.a_box)), -z[3] / s.params.dt))
        z = bicycle.step(z, [Delta[-1], alpha[-1]], s.params)
    return np.array(Delta), np.array(alpha)


def brake_plan(s: Settings, z0):
    """Controls Delta, alpha (T_p,) that hold the current lane (lane_plan) braking at s.brake to a stop."""
    return lane_plan(s, z0, s.brake)


def repaired(s: Settings, obs: Observation, source, safety, st: admm.ADMMState):
    """The plan st with its controls repaired (planner.repair) until its checked rollout is acceptable, at most
    s.repair_iters steps, with its min b_i (m^2) and the predictor's values under it; None when no repair passes."""
    Phi_1, Phi_2, _ = costs(s, obs.u_prev)
    W = linalg.block_diag(Phi_1.P, Phi_2.P)
    Delta, alpha = st.Delta, st.alpha
    for _ in range(s.repair_iters):
        Z = simulate(obs.z0, Delta, alpha, s.params)
        b, Jb = safety.linearize(Z)
        Delta, alpha = repair.repair_step(obs.z0, Delta, alpha, Z, b[:safety.n_b], Jb[:safety.n_b], s.params, W,
                                          s.delta_box, s.a_box, s.check_steps, s.repair_margin, s.osqp)
        Z, values = rollout(s, obs, source, Delta, alpha)
        b_min = checked_b(s, values)
        if acceptable(s, obs, source, b_min):
            return st._replace(Delta=Delta, alpha=alpha, Z=Z, zstate=None), b_min, values
    return None


def fallback(s: Settings, obs: Observation, source, warm, why: str) -> StepResult:
    """The shifted previous plan if the predictor still finds it safe, else braking in the current lane.

    Without a finite ego state there is nothing to steer by: the shifted plan is applied unchecked, or straight braking.
    """
    z_ok, seen = np.all(np.isfinite(obs.z0)), np.all(np.isfinite(obs.z0)) and np.all(np.isfinite(obs.history))
    if warm is not None:
        prev = shift(warm)._replace(zstate=None)
        b_min, Z = plan_safe(s, obs, source, prev.Delta, prev.alpha) if seen else (np.nan, prev.Z)
        if not seen or acceptable(s, obs, source, b_min):
            return StepResult(u=np.array([prev.Delta[0], prev.alpha[0]]), plan=prev._replace(Z=Z) if z_ok else None,
                              J=J_of(s, obs.u_prev, prev.Delta, prev.alpha, Z), iters=0, reason="fallback", F_norm=np.nan,
                              b_min=b_min, slack=np.nan, fallback=f"{why}; shifted previous plan")
    if not z_ok:
        return StepResult(u=np.array([0.0, s.brake]), plan=None, J=np.nan, iters=0, reason="fallback", F_norm=np.nan,
                          b_min=np.nan, slack=np.nan, fallback=f"{why}; braking straight")
    Delta, alpha = brake_plan(s, obs.z0)
    Z = simulate(obs.z0, Delta, alpha, s.params)
    plan = admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p))
    return StepResult(u=np.array([Delta[0], alpha[0]]), plan=plan, J=J_of(s, obs.u_prev, Delta, alpha, Z), iters=0,
                      reason="fallback", F_norm=np.nan, b_min=np.nan, slack=np.nan, fallback=f"{why}; braking in lane")


def solve_from(s: Settings, obs: Observation, source, start: admm.ADMMState, zstep):
    """ADMM (Algorithm 1) from `start`, then the check of its plan, repaired if it fails (planner.repair): (StepResult
    with fallback "" or None, why it failed). Raises what the solvers raise."""
    prob, solvers, start = build(s, obs, source, None, zstep, start)
    st, solve = (jit_admm if s.core == "compiled" else admm).admm_solve(prob, solvers, start, *s.admm)
    if not all(np.all(np.isfinite(a)) for a in (st.Delta, st.alpha, st.Z, st.mu)):
        return None, "non-finite iterate"
    values = rollout(s, obs, source, st.Delta, st.alpha)[1]
    b_min, reason = min(checked_b(s, values), solve.zinfo.get("b_min", np.inf)), solve.reason
    if not acceptable(s, obs, source, b_min):
        why = "infeasible linearisation" if solve.zinfo.get("infeasible") else "unsafe plan"
        try:
            fixed = repaired(s, obs, source, solvers.zstep.safety, st) if s.repair_iters else None
        except (SolverFailure, np.linalg.LinAlgError) as e:
            why, fixed = f"{why}, repair failed ({e})", None
        if fixed is None:
            return None, f"{why} (min b_i {b_min:.2f} m^2)"
        (st, b_min, values), reason = fixed, f"{reason}, repaired"
    return StepResult(u=np.array([st.Delta[0], st.alpha[0]]), plan=st, J=prob.J(st), iters=solve.iters, reason=reason,
                      F_norm=solve.F_norm, b_min=b_min, slack=solve.zinfo.get("slack", 0.0), fallback="",
                      zstop=solve.zinfo.get("termination_reason", ""), c_min=solve.zinfo.get("c_min", np.nan),
                      braking=imposed(s, obs, values), follower_braking=follower_braking(s, obs, st.Z, values)), ""


def shifted_rank(s: Settings) -> float:
    """The shifted plan's rank among the starts' (1, 2, ... in the order of s.starts) in choose: after those that lean
    in (offset > 0), before those that wait in lane. When the lean start's plan fails or imposes braking, the shifted
    plan, leaning already, goes on asking the driver behind instead of dropping back to the lane centre (on tuning world
    3,000,001 the ego swung between the two for 4 s beside a driver who would have yielded)."""
    return sum(float(offset) > 0 for offset, _, _ in s.starts) + 0.5


def choose(s: Settings, plans, y0: float):
    """The plan to apply among solved (name, StepResult, rank), the ego at lateral position y0 (m): with several, the
    least braking above b_courtesy (m/s^2), predicted or the nominal follower's (without courtesy rows, b_safe is not
    the planner's to judge: none), then a merge (a plan that ends in the target lane, or s.progress nearer y_ref than
    y0) by the lowest cost J; without one, the lowest rank (the order of s.starts, the shifted plan's solve at
    shifted_rank), so an ego that cannot merge yet waits as the first start says instead of pressing on beside the gap
    (the scenario's J, which pulls towards y_ref, would choose that), then J."""
    if len(plans) == 1:
        return plans[0]
    excess = lambda r: 0.0 if s.b_courtesy is None else max(0.0, r.braking - s.b_courtesy, r.follower_braking - s.b_courtesy)
    merges = lambda r: (s.road.lane_of(r.plan.Z[-3]) == s.road.lane_of(s.y_ref)
                        or abs(s.y_ref - y0) - abs(s.y_ref - r.plan.Z[-3]) >= s.progress)
    return min(plans, key=lambda p: (excess(p[1]), (0, p[1].J) if merges(p[1]) else (1, p[2], p[1].J)))


def mpc_step(s: Settings, obs: Observation, source, warm, zstep) -> StepResult:
    """One ADMM-NNMPC step (Algorithm 1's inner loop) with its fallbacks: from the shifted previous plan and, with
    s.starts, the solves of lane_starts, the best checked plan (choose); zstep: the Z-step class with its settings bound
    (conf/zstep/, bound by conf/solver/admm.yaml)."""
    if not (np.all(np.isfinite(obs.history)) and np.all(np.isfinite(obs.z0)) and np.all(np.isfinite(obs.u_prev))):
        return fallback(s, obs, source, warm, "non-finite observation")
    plans, whys = [], []
    solves = [("shifted", start_point(s, obs, warm)[0], s), *lane_starts(s, obs)]
    for rank, (name, start, aim) in enumerate(solves):
        try:
            result, why = solve_from(aim, obs, source, start, zstep)
        except (SolverFailure, np.linalg.LinAlgError, FloatingPointError) as e:
            result, why = None, f"solver failure ({e})"
        except UserError:  # the user's to fix (a missing optional solver): one line, not a fallback every step
            raise
        except Exception as e:  # anything else the config check let through (planner.setup): a fallback with its reason
            result, why = None, f"step error ({type(e).__name__}: {str(e)[:200]})"
        if result is None:
            whys.append((name, why))
        elif aim is s:
            plans.append((name, result, shifted_rank(s)))
        else:  # judged by the scenario's own cost
            plans.append((name, result._replace(J=J_of(s, obs.u_prev, result.plan.Delta, result.plan.alpha, result.plan.Z)), rank))
    if not plans:
        why = whys[0][1] if len({w for _, w in whys}) == 1 else "; ".join(f"{n}: {w}" for n, w in whys)
        try:
            return fallback(s, obs, source, warm, why)
        except Exception:  # the predictor cannot judge the shifted plan either: brake in lane
            return fallback(s, obs, source, None, why)
    name, result, _ = choose(s, plans, obs.z0[1])
    return result if len(plans) == 1 and not s.starts else result._replace(reason=f"{result.reason}, from {name}")
