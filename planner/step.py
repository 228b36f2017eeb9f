"""One receding-horizon ADMM-NNMPC step: the strategy's candidate starts -> ADMM (Algorithm 1) from each -> the safeguard
(check, repair, fallback) -> the strategy's choice among the plans that passed.

A step never raises for a bad observation, a solver failure, any other error in building or solving it, or an unsafe
result: it returns the fallback (planner.safeguard) with the reason.
"""
import numpy as np

from core.jobs import UserError
from planner import admm, safeguard
from planner.mpc import J_of, Observation, Settings, StepResult, build
from planner.qp import SolverFailure


def offered(s: Settings, obs: Observation, source, plan: admm.ADMMState):
    """A strategy's plan as it is, through the safeguard's check: (StepResult, "") or (None, why it failed)."""
    values = safeguard.rollout(s, obs, source, plan.Delta, plan.alpha)[1]
    b_min = safeguard.checked_b(s, values)
    if not safeguard.acceptable(s, obs, source, b_min):
        return None, f"unsafe plan (min b_i {b_min:.2f} m^2)"
    return StepResult(u=np.array([plan.Delta[0], plan.alpha[0]]), plan=plan, J=J_of(s, obs.u_prev, *plan[:3]), iters=0,
                      reason="as planned", F_norm=np.nan, b_min=b_min, slack=0.0, fallback="",
                      braking=safeguard.imposed(s, obs, values), values=values), ""


def solve(s: Settings, aim: Settings | None, obs: Observation, source, start: admm.ADMMState, zstep):
    """ADMM (Algorithm 1) with `aim`'s settings from `start`, then the safeguard's check of its plan, repaired if it fails:
    (StepResult with fallback "" and J by the scenario's own settings s, or None; why it failed); aim None: `start` as it
    is, checked. Raises what the solvers raise."""
    if aim is None:
        return offered(s, obs, source, start)
    prob, solvers, start = build(aim, obs, source, None, zstep, start)
    st, out = aim.core.solve(prob, solvers, start, aim.admm.max_iters, aim.admm.tol_F, aim.admm.tol_step)
    if not all(np.all(np.isfinite(a)) for a in (st.Delta, st.alpha, st.Z, st.mu)):
        return None, "non-finite iterate"
    values = safeguard.rollout(aim, obs, source, st.Delta, st.alpha)[1]
    b_min, reason = min(safeguard.checked_b(aim, values), out.zinfo.get("b_min", np.inf)), out.reason
    if not safeguard.acceptable(aim, obs, source, b_min):
        why = "infeasible linearisation" if out.zinfo.get("infeasible") else "unsafe plan"
        try:
            fixed = safeguard.repaired(aim, obs, source, solvers.zstep.safety, st) if aim.safeguard.repair_iters else None
        except (SolverFailure, np.linalg.LinAlgError) as e:
            why, fixed = f"{why}, repair failed ({e})", None
        if fixed is None:
            return None, f"{why} (min b_i {b_min:.2f} m^2)"
        (st, b_min, values), reason = fixed, f"{reason}, repaired"
    return StepResult(u=np.array([st.Delta[0], st.alpha[0]]), plan=st, J=J_of(s, obs.u_prev, st.Delta, st.alpha, st.Z),
                      iters=out.iters, reason=reason, F_norm=out.F_norm, b_min=b_min, slack=out.zinfo.get("slack", 0.0),
                      fallback="", zstop=out.zinfo.get("termination_reason", ""), c_min=out.zinfo.get("c_min", np.nan),
                      braking=safeguard.imposed(aim, obs, values), values=values), ""


def guarded(part):
    """part() -> (value or None, why), with any error in it a None and its reason; a UserError (the user's to fix, a
    missing optional solver) is raised, one line, not a fallback every step."""
    try:
        return part()
    except (SolverFailure, np.linalg.LinAlgError, FloatingPointError) as e:
        return None, f"solver failure ({e})"
    except UserError:
        raise
    except Exception as e:  # anything else the config check let through (planner.setup): a fallback with its reason
        return None, f"step error ({type(e).__name__}: {str(e)[:200]})"


def mpc_step(s: Settings, obs: Observation, source, warm, zstep) -> StepResult:
    """One ADMM-NNMPC step: ADMM from each of s.strategy's candidate starts, the safeguard on each plan, s.strategy's
    choice among those that pass, or the fallback; zstep: the Z-step class with its settings bound (conf/zstep/, bound
    by conf/solver/admm.yaml)."""
    if not safeguard.observed(obs):
        return safeguard.fallback(s, obs, source, warm, "non-finite observation")
    starts, why = guarded(lambda: (s.strategy.candidates(s, obs, warm, source), ""))
    plans, whys = [], [] if starts is not None else [("candidates", why)]
    for start in starts or ():
        result, why = guarded(lambda: solve(s, start.aim, obs, source, start.plan, zstep))
        if result is None:
            whys.append((start.name, why))
        else:
            plans.append((start, result))
    if not plans:
        why = whys[0][1] if len({w for _, w in whys}) == 1 else "; ".join(f"{n}: {w}" for n, w in whys)
        try:
            return safeguard.fallback(s, obs, source, warm, why)
        except Exception:  # the predictor cannot judge the shifted plan either: brake in lane
            return safeguard.fallback(s, obs, source, None, why)
    start, result = s.strategy.choose(s, obs, plans)
    return result if len(starts) == 1 else result._replace(reason=f"{result.reason}, from {start.name}")
