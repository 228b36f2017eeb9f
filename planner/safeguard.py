"""The safeguard every solver's plan passes before it is applied (ADMM, IPOPT and NNMPC share it): the check of its
nonlinear rollout against the predictor, the repair of a plan that misses it (planner.repair), and the fallback when
nothing passes (the shifted previous plan if the predictor still finds it safe, else braking in lane)."""
import numpy as np
from scipy import linalg

from core.rollout import b_i, braking, ego_xy
from planner import admm, repair
from planner.jit_rollout import values
from planner.mpc import BRAKE, J_of, Observation, Settings, StepResult, brake_plan, costs, shift, simulate

CHECK_STEPS = 2  # steps of a plan's nonlinear rollout the check reads: only its start is applied, the rest is replanned
CHECK_TOL = 0.05  # m^2: b_i violation tolerated over those steps
REPAIR_MARGIN = 0.1  # m^2: b_i a repair step aims for over them on the linearised rollout


def rollout(s: Settings, obs: Observation, source, Delta, alpha, Z=None):
    """The nonlinear rollout Z of (Delta, alpha) (given: simulate's, already done) and the predictor's values
    (T_p, SLOTS, 2) under it."""
    Z = simulate(obs.z0, Delta, alpha, s.params) if Z is None else Z
    return Z, values(source, obs.history, ego_xy(Z, s.T_p))


def yaw_excess(s: Settings, Z) -> float:
    """How far (rad, >= 0) the yaw of a rollout Z (4T_p,) leaves psi_box over the first check_steps: beyond it a
    superellipse safety shape (mpc.shape > 2) no longer covers the two bodies (mpc.check_shape), so its b_i says nothing;
    0 for the ellipse, whose cover is its config's to choose."""
    if s.shape == 2:
        return 0.0
    psi = Z[2::4][:CHECK_STEPS]
    return float(np.max(np.maximum(psi - s.psi_box[1], s.psi_box[0] - psi), initial=0.0))


def checked_b(s: Settings, values) -> float:
    """min b_i (m^2) over the first check_steps of a rollout's predictor values (T_p, SLOTS, 2)."""
    return float(b_i(values, s.R, s.stretch, s.shape)[:, :CHECK_STEPS].min(initial=np.inf))


def plan_safe(s: Settings, obs: Observation, source, Delta, alpha):
    """min b_i (m^2) over the first check_steps of the nonlinear rollout of (Delta, alpha) against the predictor's reaction."""
    Z, values = rollout(s, obs, source, Delta, alpha)
    return checked_b(s, values), Z


YAW_TOL = 1e-3  # rad a checked rollout's yaw may leave psi_box by: the repair's QP meets its rows to about this


def acceptable(s: Settings, b_min: float, Z=None) -> bool:
    """Whether a plan whose checked rollout (Z, when given) has min b_i = b_min (m^2) may be applied: b_min >= -check_tol
    and its yaw within psi_box (YAW_TOL)."""
    return b_min >= -CHECK_TOL and (Z is None or yaw_excess(s, Z) <= YAW_TOL)


def why_not(s: Settings, b_min: float, Z) -> str:
    """Why a checked rollout is not acceptable: its min b_i (m^2), or its yaw beyond psi_box (rad)."""
    excess = yaw_excess(s, Z)
    return f"yaw {excess:.2f} rad beyond mpc.psi_box" if excess > YAW_TOL else f"min b_i {b_min:.2f} m^2"


def imposed(s: Settings, obs: Observation, values) -> float:
    """The hardest braking (m/s^2, >= 0) the predictor expects of another car, from its values (T_p, SLOTS, 2) over a
    plan's rollout."""
    return float(braking(values, obs.history, s.params.dt))


def repaired(s: Settings, obs: Observation, source, safety, st: admm.ADMMState):
    """The plan st with its controls repaired (planner.repair) until its checked rollout is acceptable, at most
    s.repair_iters steps, with its min b_i (m^2) and the predictor's values under it; None when no repair passes."""
    Phi_1, Phi_2, _ = costs(s, obs.u_prev)
    W = linalg.block_diag(Phi_1.P, Phi_2.P)
    Delta, alpha = st.Delta, st.alpha
    for _ in range(s.repair_iters):
        Z = simulate(obs.z0, Delta, alpha, s.params)
        b, Jb, _ = safety.linearize(Z)
        Delta, alpha = repair.repair_step(obs.z0, Delta, alpha, Z, b[:safety.n_b], Jb[:safety.n_b], s.params, W,
                                          s.delta_box, s.a_box, s.psi_box, CHECK_STEPS,
                                          REPAIR_MARGIN)
        Z, values = rollout(s, obs, source, Delta, alpha)
        b_min = checked_b(s, values)
        if acceptable(s, b_min, Z):
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
        if not seen or acceptable(s, b_min, Z):
            return StepResult(u=np.array([prev.Delta[0], prev.alpha[0]]), plan=prev._replace(Z=Z) if z_ok else None,
                              J=J_of(s, obs.u_prev, prev.Delta, prev.alpha, Z), iters=0, reason="fallback", F_norm=np.nan,
                              b_min=b_min, slack=np.nan, fallback=f"{why}; shifted previous plan")
    if not z_ok:
        return StepResult(u=np.array([0.0, BRAKE]), plan=None, J=np.nan, iters=0, reason="fallback", F_norm=np.nan,
                          b_min=np.nan, slack=np.nan, fallback=f"{why}; braking straight")
    Delta, alpha = brake_plan(s, obs.z0)
    Z = simulate(obs.z0, Delta, alpha, s.params)
    plan = admm.ADMMState(Delta, alpha, Z, np.zeros(4 * s.T_p))
    return StepResult(u=np.array([Delta[0], alpha[0]]), plan=plan, J=J_of(s, obs.u_prev, Delta, alpha, Z), iters=0,
                      reason="fallback", F_norm=np.nan, b_min=np.nan, slack=np.nan, fallback=f"{why}; braking in lane")


def observed(obs: Observation) -> bool:
    """Whether the observation is finite throughout (ego state, last input, history): a step on anything else falls back."""
    return bool(np.all(np.isfinite(obs.history)) and np.all(np.isfinite(obs.z0)) and np.all(np.isfinite(obs.u_prev)))
