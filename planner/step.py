"""One receding-horizon ADMM-NNMPC step: the strategy's candidate starts -> ADMM (Algorithm 1) from each -> the safeguard
(check, repair, fallback) -> the strategy's choice among the plans that passed.

A step never raises for a bad observation, a solver failure, any other error in building or solving it, or an unsafe
result: it returns the fallback (planner.safeguard) with the reason.
"""
import numpy as np

from core.jobs import UserError
from planner import admm, jit_admm, jit_rollout, safeguard
from planner.mpc import J_of, Observation, Settings, StepResult, alike, build, simulate
from planner.qp import SolverFailure


def offered(s: Settings, obs: Observation, source, plan: admm.ADMMState):
    """A strategy's plan as it is, through the safeguard's check: (StepResult, "") or (None, why it failed). Its Z is
    taken as its controls' nonlinear rollout (a strategy offers planned plans: mpc.planned), not simulated again."""
    values = safeguard.rollout(s, obs, source, plan.Delta, plan.alpha, plan.Z)[1]
    b_min = safeguard.checked_b(s, values)
    if not safeguard.acceptable(s, obs, source, b_min):
        return None, f"unsafe plan (min b_i {b_min:.2f} m^2)"
    return StepResult(u=np.array([plan.Delta[0], plan.alpha[0]]), plan=plan, J=J_of(s, obs.u_prev, *plan[:3]), iters=0,
                      reason="as planned", F_norm=np.nan, b_min=b_min, slack=0.0, fallback="",
                      braking=safeguard.imposed(s, obs, values), values=values), ""


def solve(s: Settings, aim: Settings | None, obs: Observation, source, start: admm.ADMMState, zstep):
    """ADMM (Algorithm 1) with `aim`'s settings from `start`, then the safeguard's check of its plan (checked): (StepResult
    with fallback "" and J by the scenario's own settings s, or None; why it failed); aim None: `start` as it is, checked.
    Raises what the solvers raise."""
    if aim is None:
        return offered(s, obs, source, start)
    prob, solvers, start = build(aim, obs, source, None, zstep, start)
    st, out = aim.core.solve(prob, solvers, start, aim.admm.max_iters, aim.admm.tol_F, aim.admm.tol_step)
    return checked(s, aim, obs, source, solvers, st, out)


def checked(s: Settings, aim: Settings, obs: Observation, source, solvers, st: admm.ADMMState, out: admm.Solve,
            Z=None):
    """The safeguard's check of ADMM's plan st (solved with `aim`'s settings and `solvers`; Z: its nonlinear rollout
    when known), repaired if it fails: as solve's result."""
    if not all(np.isfinite(a).all() for a in (st.Delta, st.alpha, st.Z, st.mu)):  # the method: 60% of np.all's time
        return None, "non-finite iterate"
    values = safeguard.rollout(aim, obs, source, st.Delta, st.alpha, Z)[1]
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


def solve_all(s: Settings, obs: Observation, source, starts, zstep) -> list:
    """solve from every Start of a step, each guarded: [(StepResult or None, why)]. Where the compiled core runs the
    source's predictor itself (cv, the student) the starts' ADMM solves run in one compiled call
    (planner.jit_admm.compiled_solves), with their plans as solve's own; for other sources, one solve after another."""
    aimed = [k for k, start in enumerate(starts) if start.aim is not None]
    one_by_one = lambda: [guarded(lambda: solve(s, start.aim, obs, source, start.plan, zstep)) for start in starts]
    if (len(aimed) < 2 or any(starts[k].aim.core.solve is not jit_admm.admm_solve for k in aimed)
            or jit_rollout.compiled_params(source) is None):
        return one_by_one()
    built = {}
    for k in aimed:  # a start aiming only elsewhere than one set up before shares that one's set-up (mpc.build's like)
        like = next((b for j, (b, _) in built.items() if b is not None and alike(starts[j].aim, starts[k].aim)), None)
        built[k] = guarded(lambda: (build(starts[k].aim, obs, source, None, zstep, starts[k].plan, like), ""))
    ok = [k for k in aimed if built[k][0] is not None and jit_admm.together(built[k][0][1])]
    admm_of = lambda k: starts[k].aim.admm
    try:
        loops = dict(zip(ok, jit_admm.compiled_solves(
            [(*built[k][0], admm_of(k).max_iters, admm_of(k).tol_F, admm_of(k).tol_step) for k in ok]) if ok else []))
    except Exception:  # an error inside the joint call (or starts unlike each other): each start's own, one by one
        return one_by_one()

    def one(k, start):
        if start.aim is None:
            return offered(s, obs, source, start.plan)
        if k not in loops:  # its set-up failed (built's reason), or it does not solve in one call
            return built[k] if built[k][0] is None else solve(s, start.aim, obs, source, start.plan, zstep)
        solvers = built[k][0][1]
        return checked(s, start.aim, obs, source, solvers, *jit_admm.solved(loops[k], solvers), rolled.get(k))

    rolled = guarded(lambda: (rollouts(obs, [(k, starts[k].aim.params, loops[k].it) for k in loops]), ""))[0] or {}
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
