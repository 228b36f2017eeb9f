"""One receding-horizon ADMM-NNMPC step: the strategy's candidate starts -> ADMM (Algorithm 1) from each -> the safeguard
(check, repair, fallback) -> the strategy's choice among the plans that passed.

A step never raises for a bad observation, a solver failure, any other error in building or solving it, or an unsafe
result: it returns the fallback (planner.safeguard) with the reason.
"""
import numpy as np

from core.jobs import UserError
from planner import admm, safeguard
from planner.mpc import J_of, Observation, Settings, StepResult, alike, build, simulate
from planner.qp import SolverFailure


def offered(s: Settings, obs: Observation, source, plan: admm.ADMMState):
    """A strategy's plan as it is, through the safeguard's check: (StepResult, "") or (None, why it failed). Its Z is
    taken as its controls' nonlinear rollout (a strategy offers planned plans: mpc.planned), not simulated again."""
    values = safeguard.rollout(s, obs, source, plan.Delta, plan.alpha, plan.Z)[1]
    b_min = safeguard.checked_b(s, values)
    if not safeguard.acceptable(s, b_min, plan.Z):
        return None, f"unsafe plan ({safeguard.why_not(s, b_min, plan.Z)})"
    return StepResult(u=np.array([plan.Delta[0], plan.alpha[0]]), plan=plan, J=J_of(s, obs.u_prev, *plan[:3]), iters=0,
                      reason="as planned", F_norm=np.nan, b_min=b_min, slack=0.0, fallback="",
                      braking=safeguard.imposed(s, obs, values), values=values), ""


def checked(s: Settings, aim: Settings, obs: Observation, source, solvers, st: admm.ADMMState, out: admm.Solve,
            Z=None):
    """The safeguard's check of ADMM's plan st (solved with `aim`'s settings and `solvers`; Z: its nonlinear rollout
    when known), repaired if it fails: as solve's result."""
    if not all(np.isfinite(a).all() for a in (st.Delta, st.alpha, st.Z, st.mu)):  # the method: 60% of np.all's time
        return None, "non-finite iterate"
    Z, values = safeguard.rollout(aim, obs, source, st.Delta, st.alpha, Z)
    b_min, reason = min(safeguard.checked_b(aim, values), out.zinfo.get("b_min", np.inf)), out.reason
    if not safeguard.acceptable(aim, b_min, Z):
        why = "infeasible linearisation" if out.zinfo.get("infeasible") else "unsafe plan"
        try:
            fixed = safeguard.repaired(aim, obs, source, solvers.zstep.safety, st) if aim.repair_iters else None
        except (SolverFailure, np.linalg.LinAlgError) as e:
            why, fixed = f"{why}, repair failed ({e})", None
        if fixed is None:
            return None, f"{why} ({safeguard.why_not(aim, b_min, Z)})"
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


def solve_all(s: Settings, obs: Observation, source, starts, zstep) -> list:
    """ADMM (Algorithm 1) from every Start of a step with its aim's settings, then the safeguard's check of its plan
    (checked), each guarded: [(StepResult or None, why)]; a Start without an aim is offered as it is. A start aiming
    only elsewhere than one set up before shares that one's set-up (mpc.build's like); the solves whose Z-step's
    predictor is written as kernels (admm.compiled) run in one compiled call (admm.compiled_solves), the others one
    after another, each plan as solved alone."""
    built = {}
    for k, start in enumerate(starts):
        if start.aim is not None:
            like = next((b for j, (b, _) in built.items() if b is not None and alike(starts[j].aim, start.aim)), None)
            built[k] = guarded(lambda: (build(start.aim, obs, source, None, zstep, start.plan, like), ""))
    ok = [k for k, (b, _) in built.items() if b is not None and admm.compiled(b[1])]
    stop = lambda k: (starts[k].aim.admm.max_iters, admm.TOL_F, admm.TOL_STEP)
    joint = lambda: (dict(zip(ok, admm.compiled_solves([(*built[k][0], *stop(k)) for k in ok]))), "")
    loops = (guarded(joint)[0] or {}) if ok else {}
    rolled = guarded(lambda: (rollouts(obs, [(k, starts[k].aim.params, loops[k].it) for k in loops]), ""))[0] or {}

    def one(k, start):
        if start.aim is None:
            return offered(s, obs, source, start.plan)
        if built[k][0] is None:  # its set-up failed: built's reason
            return built[k]
        prob, solvers, st = built[k][0]
        st, out = admm.solved(loops[k]) if k in loops else admm.admm_solve(prob, solvers, st, *stop(k))
        return checked(s, start.aim, obs, source, solvers, st, out, rolled.get(k))

    return [guarded(lambda: one(k, start)) for k, start in enumerate(starts)]


def rollouts(obs: Observation, plans) -> dict:
    """{k: the nonlinear rollout Z (4T_p,)} of plans [(k, bicycle params, iterate with Delta and alpha)] whose controls
    are finite and params the first such plan's, simulated together (mpc.simulate: each plan's numbers as alone)."""
    finite = [(k, p, it) for k, p, it in plans if np.isfinite(it.Delta).all() and np.isfinite(it.alpha).all()]
    batch = [(k, it) for k, p, it in finite if p == finite[0][1]]
    if not batch:
        return {}
    Z = simulate(obs.z0, np.array([it.Delta for _, it in batch]), np.array([it.alpha for _, it in batch]), finite[0][1])
    return {k: z for (k, _), z in zip(batch, Z)}


def mpc_step(s: Settings, obs: Observation, source, warm, zstep) -> StepResult:
    """One ADMM-NNMPC step: ADMM from each of s.strategy's candidate starts, the safeguard on each plan, s.strategy's
    choice among those that pass, or the fallback; zstep: the Z-step class with its settings bound (conf/zstep/, bound
    by conf/solver/admm.yaml)."""
    if not safeguard.observed(obs):
        return safeguard.fallback(s, obs, source, warm, "non-finite observation")
    starts, why = guarded(lambda: (s.strategy.candidates(s, obs, warm, source), ""))
    plans, whys = [], [] if starts is not None else [("candidates", why)]
    for start, (result, why) in zip(starts or (), solve_all(s, obs, source, starts or [], zstep)):
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
