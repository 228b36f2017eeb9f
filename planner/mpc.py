"""The MPC step's problem: its settings (eq. (5)-(8); Algorithm 1's and the strategy's nodes), what the planner sees, what
a step returns, and the paper's maths about one observation: the costs, boxes, linearisation and ADMM's set-up.

How a step runs (candidate starts -> ADMM -> safeguard -> choose) is planner.step; the safeguard (check, repair,
fallback) planner.safeguard; which plans to start from and how to choose among them, planner.strategy.
"""
from dataclasses import dataclass, fields
from typing import Any, NamedTuple

import numpy as np

from core.jobs import UserError
from core.rollout import b_i
from core.validate import HORIZON, Int, OneOf, Range, Real, check_fields, rule
from data import bicycle
from data.world import Road, Steering
from planner import admm, cost, dynamics, jit_bicycle
from planner.safety import Safety

POS, NONNEG, PAIR = Real(0, lo_open=True), Real(0), Range(strict=True)

BRAKE = -3.0  # m/s^2: deceleration of the safeguard's braking-in-lane fallback (planner.safeguard.fallback)


@dataclass(frozen=True)
class Settings:
    """One step's settings in SI units, data only, built from the `planner` config's `mpc` node (planner.setup adds the
    paper's weights, the planner's linearize and the scenario's y_ref, v_ref, x_ref (lane_end), merge_tol, road and params): the problem, eq. (5)-(8)
    about one observation, and the safeguard's repair here; the solver (`admm`) and the strategy in their own nodes.
    Each value is checked where it is defined, one UserError naming the key."""

    name: str  # the conf/mpc/ option (MLflow param `mpc`): paper | courteous | ...
    weights: cost.Weights
    y_ref: float  # m: the target lane's centre; a refined candidate's aim may be its own path instead, a tuple of T_p (Phi_3)
    v_ref: float  # m/s; likewise
    lane_y: float  # m: the target lane's centre, the scenario's y_ref, which no candidate's aim replaces
    lane_end: float  # m: where the ego's lane ends, the scenario's x_ref
    merge_tol: float  # m: merged once the ego's centre is this close to lane_y (the scenario's)
    road: Road
    params: bicycle.BicycleParams
    T_p: int = rule(HORIZON)  # prediction horizon (steps of dt), at most core.validate.MAX_T_P: a step's time grows as T_p^3
    r: float = rule(POS)  # ego's safety radius (m)
    r_i: float = rule(POS)  # the others' safety radius (m)
    eps: float = rule(NONNEG)  # safety margin (m)
    stretch: float = rule(Real(1))  # the safety ellipse's along-road semi-axis over R (core.rollout.b_i); 1: the paper's circle
    shape: float = rule(Real(2))  # the exponent p of the safety shape (core.rollout.b_i): 2 the ellipse, higher a rounded rectangle
    b_courtesy: float | None = rule(Real(0, lo_open=True, nullable=True))  # courtesy rows: nobody predicted to brake harder than this (m/s^2); None: none (the paper)
    delta_box: tuple = rule(PAIR)  # rad
    a_box: tuple = rule(PAIR)  # m/s^2
    psi_box: tuple = rule(PAIR)  # rad
    v_box: tuple = rule(PAIR)  # m/s
    y_margin: float = rule(NONNEG)  # how far the ego's centre may leave the outer lane centres (m)
    linearize: str = rule(OneOf(("last_observed", "along_plan")))
    repair_iters: int = rule(Int(0))  # repair steps (planner.repair) for a plan that fails the safeguard's check; 0: none, the paper
    admm: admm.Settings  # the solver: Algorithm 1's penalty and stopping
    strategy: Any  # which plans to solve from and which to apply (planner.strategy)

    def __post_init__(self):
        check_fields(self, "mpc")
        check_shape(self)

    @property
    def R(self) -> float:
        """Single-circle safety distance r + r_i + eps (m), eq. (6)."""
        return self.r + self.r_i + self.eps


def check_shape(s: Settings) -> None:
    """One UserError unless a superellipse safety shape (mpc.shape > 2) covers two of the road's bodies, the ego's
    yawed anywhere within psi_box: the corner of their bounding boxes' sum must lie inside it. The ellipse (shape 2) is
    the paper's circle or the scenario's own and is left to its config."""
    if s.shape == 2:
        return
    half_l, half_w, psi = s.road.car_length / 2, s.road.car_width / 2, max(abs(a) for a in s.psi_box)
    dx = half_l + half_l * np.cos(psi) + half_w * np.sin(psi)
    dy = half_w + half_l * np.sin(psi) + half_w * np.cos(psi)
    if b_i(np.array([[[0.0, 0.0], [dx, dy]]]), s.R, s.stretch, s.shape)[0, 0] > 0:
        raise UserError(f"mpc.shape={s.shape:g} with R={s.R:g} m and mpc.stretch={s.stretch:g} does not cover two "
                        f"{s.road.car_length:g} x {s.road.car_width:g} m bodies with the ego yawed up to {psi:g} rad "
                        f"(mpc.psi_box): raise mpc.r or mpc.stretch, or narrow mpc.psi_box")


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
    follower_braking: float = np.nan  # the hardest braking of a strategy's nominal follower behind the plan (m/s^2), where it has one
    values: np.ndarray | None = None  # the predictor's rollout (T_p, SLOTS, 2) under the plan's controls, where checked


def simulate(z0, Delta, alpha, params):
    """Nonlinear bicycle rollout of the controls Delta, alpha (..., T_p) from z0 (4,): Z (..., 4T_p) stacking
    z(1..T_p), each plan as alone (compiled: planner.jit_bicycle.simulate; data.bicycle.step's numbers to rounding)."""
    D, a = np.broadcast_arrays(np.asarray(Delta, float), np.asarray(alpha, float))
    flat = lambda u: np.ascontiguousarray(u.reshape(-1, u.shape[-1]))
    Z = jit_bicycle.simulate(np.asarray(z0, float), flat(D), flat(a), params.l_f, params.l_r, params.dt)
    return Z.reshape(D.shape[:-1] + (4 * D.shape[-1],))


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


def lane_plan(s: Settings, z0, a):
    """Controls Delta, alpha (T_p,) that steer to the current lane's centre (straddling: the lane away from y_ref) at
    acceleration a (m/s^2) within the box, never into reverse (the bicycle's v may go negative)."""
    Delta, alpha, _ = lane_plans(s, z0, [a])
    return Delta[0], alpha[0]


def wholly_in(road: Road, y, lane_y: float) -> bool:
    """Whether a car whose centre is at lateral position y (m) lies wholly inside the lane centred at lane_y (m)."""
    return abs(float(y) - lane_y) <= (road.lane_width - road.car_width) / 2


def lane_plans(s: Settings, z0, accels):
    """lane_plan for each acceleration of accels (n,) (m/s^2), rolled out together, with the rollouts: Delta, alpha
    (n, T_p) and Z (n, 4T_p) as simulate's, each plan as alone (planner.jit_bicycle.lane_plans, by the world drivers'
    steering law)."""
    z = np.asarray(z0, float)
    lane_y = s.road.centre(s.road.lane_of(z[1]))
    if not wholly_in(s.road, z[1], lane_y):  # straddling: abort, back away from y_ref
        lane_y = s.road.centre(s.road.lane_of(z[1] - np.sign(s.y_ref - z[1]) * s.road.lane_width / 2))
    a = np.clip(np.asarray(accels, float), *s.a_box)
    return jit_bicycle.lane_plans(z, float(lane_y), np.ascontiguousarray(a, float), s.T_p, car(s, Steering()))


def car(s: Settings, law: Steering) -> jit_bicycle.Car:
    """The planned ego as jit_bicycle.drive moves it: the scenario's bicycle, a_box, and `law` within delta_box."""
    p, (lo, hi) = s.params, s.delta_box
    law = Steering(*map(float, law[:4]), max(float(law.delta_lo), float(lo)), min(float(law.delta_hi), float(hi)))
    return jit_bicycle.Car(float(p.l_f), float(p.l_r), float(p.dt), (float(s.a_box[0]), float(s.a_box[1])), law)


def brake_plan(s: Settings, z0):
    """Controls Delta, alpha (T_p,) that hold the current lane (lane_plan) braking at BRAKE to a stop."""
    return lane_plan(s, z0, BRAKE)


def planned(s: Settings, z0, Delta, alpha, Z=None) -> admm.ADMMState:
    """An ADMM start from controls (Delta, alpha): their nonlinear rollout (Z: simulate's, already done) and mu = 0."""
    Z = simulate(z0, Delta, alpha, s.params) if Z is None else Z
    return admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p))


def warm_start(s: Settings, obs: Observation, warm: admm.ADMMState | None) -> admm.ADMMState:
    """Where a step's solver starts: the shifted previous plan, or zero inputs rolled out (cold)."""
    if warm is None:
        return planned(s, obs.z0, np.zeros(s.T_p), np.zeros(s.T_p))
    return shift(warm)._replace(zstate=None)


def start_point(s: Settings, obs: Observation, warm: admm.ADMMState | None):
    """warm_start's start and the dynamics linearised for it; shared by ADMM and solver=ipopt so both solve the same
    problem from the same point."""
    start = warm_start(s, obs, warm)
    return start, linearization(s, obs, start)


def linearization(s: Settings, obs: Observation, start: admm.ADMMState):
    """Eq. (5)'s dynamics for a solve from `start`: about the last observed state, or along the start's plan."""
    plan = (start.Delta, start.alpha, start.Z) if s.linearize == "along_plan" else None
    return dynamics.linearize(np.asarray(obs.z0, float), obs.u_prev[0], obs.u_prev[1], s.params, s.T_p, plan)


def courtesy(s: Settings, z0):
    """The Safety's courtesy argument: (dt s, b_c m/s^2), or None without courtesy rows or once the ego at z0 is wholly
    inside the target lane: there a car behind it braking for it can only be helped by leaving the lane, which the
    safety shape does not cover (issue 74: a plan steered out of the lane to -0.64 rad and was hit)."""
    return None if s.b_courtesy is None or wholly_in(s.road, z0[1], s.lane_y) else (s.params.dt, float(s.b_courtesy))


def build(s: Settings, obs: Observation, source, warm: admm.ADMMState | None, zstep, start: admm.ADMMState = None,
          like=None):
    """The step's Problem (eq. (5) by linearization), its Solvers (the Z-step built by `zstep`, a planner.zstep class
    with its settings bound) and the ADMM start, Z clipped to the state box: `start`, or warm_start's from warm. like:
    build's result for settings `alike` these, whose set-up is reused but for Phi_3 and the Z-step (the same numbers)."""
    start = warm_start(s, obs, warm) if start is None else start
    if like is None:
        lo, hi = state_box(s)
        prob = admm.Problem(linearization(s, obs, start), *costs(s, obs.u_prev), float(s.admm.rho), tuple(s.delta_box),
                            tuple(s.a_box), lo, hi)
        safety = Safety(source, obs.history, s.R, s.T_p, courtesy(s, obs.z0), s.stretch, s.shape)
        solvers = admm.solvers(prob, zstep, safety)
    else:
        prob = like[0]._replace(Phi_3=cost.Phi_3(s.T_p, s.weights, s.y_ref, s.v_ref))
        solvers = like[1]._replace(zstep=zstep(prob, like[1].zstep.safety))
    return prob, solvers, start._replace(Z=np.clip(start.Z, prob.z_lo, prob.z_hi))


REFERENCES = ("y_ref", "v_ref")  # what a multi-start step's starts may aim at apart and still share their set-up


def alike(a: Settings, b: Settings) -> bool:
    """Whether a step with settings b sets up as one with a but for Phi_3 and the Z-step (build's `like`): the same
    settings (the same objects, as dataclasses.replace keeps them) but for the references, the dynamics linearised
    about the last observed state (not along a start's plan)."""
    return a.linearize == "last_observed" and all(getattr(a, f.name) is getattr(b, f.name) for f in fields(Settings)
                                                  if f.compare and f.name not in REFERENCES)
