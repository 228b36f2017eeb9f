"""The full-NLP baseline (`solver=ipopt`): one MPC step written as a single NLP in CasADi and solved by IPOPT.

The same problem ADMM splits (planner.mpc): decision variables (Delta, alpha, Z); the linearised dynamics
A Delta + B alpha + C Z + D = 0 with the matrices planner.dynamics builds; J = Phi_1 + Phi_2 + Phi_3 of planner.cost; the
same boxes; and b_i(Z) >= 0 on the predictor's Remark-2 rollout written symbolically. The rollout is core.rollout's own
recursion run over numpy arrays of CasADi scalars, so CV and analytic are their numpy formulas verbatim and the student is
its float64 weights with GELU by erf. IPOPT gets exact first and second derivatives of that expression from CasADi.
The NLP is built once per (source, T_p, T_obs, R, stretch, p, weights, IPOPT options) and reused: z0, u_prev (through A, B, C, D and
the rate terms), the history and the references are its parameters. `pip install -e '.[ipopt]'` installs CasADi.
"""
from functools import lru_cache
from typing import Any, NamedTuple

import numpy as np

from core.jobs import UserError
from core.rollout import SLOTS, b_i, rollout
from distill.analytic import Analytic
from distill.models import StudentPredictor
from distill.predictors import ConstantVelocity
from planner import admm, cost, mpc, safeguard
from planner.gradients import Autodiff, ExactLocal

SUPPORTED = "cv, analytic, student"


def import_casadi():
    """The casadi module; one UserError naming the extra when it is not installed."""
    try:
        import casadi
    except ModuleNotFoundError as e:
        if (e.name or "").split(".")[0] != "casadi":
            raise
        raise UserError("solver=ipopt needs CasADi, which is not installed; run pip install -e '.[ipopt]'") from None
    return casadi


def student_phi(weights, s):
    """The GELU student (distill.student) over a window of CasADi scalars (1, T_obs, SLOTS, 2) -> next (1, SLOTS, 2), m.

    weights: [(W, b)] in float64 with the feature map folded into the first layer (GeluStudent.weights64); s (8,) the
    head bound (m per step^2)."""
    ca = import_casadi()
    layers = [(ca.DM(W), ca.DM(b)) for W, b in weights]

    def phi(window):
        h = ca.vertcat(*window.reshape(-1))
        for W, b in layers[:-1]:
            a = ca.mtimes(W, h) + b
            h = 0.5 * a * (1.0 + ca.erf(a / np.sqrt(2.0)))  # exact GELU, torch's default erf form
        W, b = layers[-1]
        t = ca.tanh(ca.mtimes(W, h) + b)
        nxt = 2.0 * window[:, -1] - window[:, -2]
        acc = np.array([s[k] * t[k] for k in range(2 * (SLOTS - 1))], dtype=object).reshape(1, SLOTS - 1, 2)
        return np.concatenate([nxt[:, :1], nxt[:, 1:] + acc], axis=1)

    return phi


def expression(source):
    """phi over numpy arrays of CasADi scalars for the source's predictor; one UserError for sources IPOPT cannot take."""
    if not isinstance(source, (ExactLocal, Autodiff)):
        raise UserError(f"solver=ipopt differentiates the predictor's CasADi expression itself; gradients={source.name} "
                        f"supplies its own derivatives and has no such expression: choose gradients={SUPPORTED.replace(', ', '|')}")
    predictor = source.predictor
    if isinstance(predictor, (ConstantVelocity, Analytic)):
        return predictor.phi  # numpy formulas that run unchanged on arrays of CasADi scalars
    if isinstance(predictor, StudentPredictor):
        return student_phi(predictor.weights, predictor.s)
    raise UserError(f"solver=ipopt cannot write the {predictor.name} predictor as a CasADi expression (the teacher would need "
                    f"l4casadi, which does not install here); it supports {SUPPORTED}")


def _block_pattern(T_p, width, diagonal):
    """(rows, cols) of the blocks planner.dynamics fills: block (tau, tau) of 4 x width and, if not `diagonal`, the 4 x 4
    blocks (tau, tau - 1) of C."""
    r, c = np.divmod(np.arange(4 * width), width)
    rows = [4 * t + r for t in range(T_p)] + ([] if diagonal else [4 * t + r for t in range(1, T_p)])
    cols = [width * t + c for t in range(T_p)] + ([] if diagonal else [4 * (t - 1) + c for t in range(1, T_p)])
    return np.concatenate(rows), np.concatenate(cols)


class NLP(NamedTuple):
    """An nlpsol over x = [Delta; alpha; Z] and where the nonzeros of A, B, C sit, (rows, cols) in CasADi's order."""

    solver: Any
    A: tuple
    B: tuple
    C: tuple


@lru_cache(maxsize=16)
def nlp(source, T_p: int, T_obs: int, R: float, stretch: float, p: float, weights: cost.Weights, options: tuple) -> NLP:
    """The step's NLP for `source`'s predictor (built once: the student's symbolic Hessian takes a while)."""
    ca = import_casadi()
    phi = expression(source)
    T4 = 4 * T_p
    Delta, alpha, Z = ca.SX.sym("Delta", T_p), ca.SX.sym("alpha", T_p), ca.SX.sym("Z", T4)
    patterns, mats, params = [], [], []
    for name, (rows, cols), n in (("A", _block_pattern(T_p, 1, True), T_p), ("B", _block_pattern(T_p, 1, True), T_p),
                                  ("C", _block_pattern(T_p, 4, False), T4)):
        sp = ca.Sparsity.triplet(T4, n, rows.tolist(), cols.tolist())
        nz = ca.SX.sym(name, sp.nnz())
        mats.append(ca.SX(sp, nz))
        params.append(nz)
        patterns.append(tuple(np.array(v) for v in sp.get_triplet()))
    D = ca.SX.sym("D", T4)
    F = mats[0] @ Delta + mats[1] @ alpha + mats[2] @ Z + D  # planner.dynamics.Dynamics.F
    J = 0.0
    for x, Phi in ((Delta, cost.Phi_1(T_p, weights, 0.0)), (alpha, cost.Phi_2(T_p, weights, 0.0)),
                   (Z, cost.Phi_3(T_p, weights, 0.0, 0.0))):
        q, r = ca.SX.sym("q", x.numel()), ca.SX.sym("r")
        J += 0.5 * ca.bilin(ca.sparsify(ca.DM(Phi.P)), x, x) + ca.dot(q, x) + r  # P is fixed by the weights; q, r carry u_prev, refs
        params += [q, r]
    history = ca.SX.sym("history", T_obs * SLOTS * 2)
    hist = np.array([history[k] for k in range(history.numel())], dtype=object).reshape(1, T_obs, SLOTS, 2)
    ego = np.array([[Z[4 * t], Z[4 * t + 1]] for t in range(T_p)], dtype=object)[None]
    b = b_i(rollout(phi, hist, ego)[0], R, stretch, p).reshape(-1)  # (N*T_p,), the order planner.safety uses
    problem = {"x": ca.vertcat(Delta, alpha, Z), "p": ca.vertcat(*params, D, history), "f": J, "g": ca.vertcat(F, *b)}
    solver = ca.nlpsol("mpc_step", "ipopt", problem, {"ipopt": dict(options), "print_time": False})
    return NLP(solver, *patterns)


def parameters(net: NLP, s: mpc.Settings, obs: mpc.Observation, dyn):
    """The NLP's parameter vector for one step: A, B, C nonzeros, q and r of Phi_1..3, D, history."""
    out = [dyn.A[net.A], dyn.B[net.B], dyn.C[net.C]]
    for Phi in mpc.costs(s, obs.u_prev):
        out += [Phi.q, [Phi.r]]
    return np.concatenate([*out, dyn.D, np.ravel(obs.history)])


def ipopt_step(s: mpc.Settings, obs: mpc.Observation, source, warm, options: dict) -> mpc.StepResult:
    """One MPC step by IPOPT from the start ADMM uses (mpc.start_point), with mpc_step's safety check and fallbacks;
    options are IPOPT's own (conf/solver/ipopt.yaml)."""
    if not safeguard.observed(obs):
        return safeguard.fallback(s, obs, source, warm, "non-finite observation")
    net = nlp(source, s.T_p, len(obs.history), s.R, s.stretch, s.shape, s.weights, tuple(sorted(options.items())))
    start, dyn = mpc.start_point(s, obs, warm)
    lo, hi = mpc.state_box(s)
    T4 = 4 * s.T_p
    n_b = (np.shape(obs.history)[1] - 1) * s.T_p
    x0 = np.concatenate([start.Delta, start.alpha, np.clip(start.Z, lo, hi)])
    try:
        sol = net.solver(x0=x0, p=parameters(net, s, obs, dyn),
                         lbx=np.concatenate([np.full(s.T_p, s.delta_box[0]), np.full(s.T_p, s.a_box[0]), lo]),
                         ubx=np.concatenate([np.full(s.T_p, s.delta_box[1]), np.full(s.T_p, s.a_box[1]), hi]),
                         lbg=np.zeros(T4 + n_b), ubg=np.concatenate([np.zeros(T4), np.full(n_b, np.inf)]))
    except RuntimeError as e:  # CasADi raises for an evaluation error it cannot hand to IPOPT
        return safeguard.fallback(s, obs, source, warm, f"solver failure ({str(e).splitlines()[0]})")
    stats = net.solver.stats()
    if not stats["success"]:
        return safeguard.fallback(s, obs, source, warm, f"IPOPT: {stats['return_status']}")
    x, g = np.asarray(sol["x"]).ravel(), np.asarray(sol["g"]).ravel()
    Delta, alpha, Z = x[:s.T_p], x[s.T_p:2 * s.T_p], x[2 * s.T_p:]
    checked, rolled = safeguard.plan_safe(s, obs, source, Delta, alpha)
    b_min = min(checked, float(g[T4:].min(initial=np.inf)))
    if not safeguard.acceptable(s, b_min, rolled):
        return safeguard.fallback(s, obs, source, warm, f"unsafe plan ({safeguard.why_not(s, b_min, rolled)})")
    plan = admm.ADMMState(Delta, alpha, Z, np.asarray(sol["lam_g"]).ravel()[:T4])  # lam_g of F = 0 plays ADMM's mu
    return mpc.StepResult(u=np.array([Delta[0], alpha[0]]), plan=plan, J=mpc.J_of(s, obs.u_prev, Delta, alpha, Z),
                          iters=int(stats["iter_count"]), reason=stats["return_status"],
                          F_norm=float(np.linalg.norm(dyn.F(Delta, alpha, Z))), b_min=b_min, slack=0.0, fallback="")
