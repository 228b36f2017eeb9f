"""The paper's own Z-update (Sec. IV-C, eq. (10)-(11); hard b_i(Z) >= 0 as in its simulation) solved by PyGranso.

PyGranso (Liang, Mitchell, Sun; a torch port of GRANSO) is a BFGS-SQP method: it takes the objective and the
inequality constraints c(Z) <= 0 as torch functions and builds their gradients by autograd, one backward pass per
constraint. With gradients=teacher the constraints are the teacher's own torch rollout (native autodiff); with any other
source b_i(Z) is a custom autograd function whose backward is that source's d b_i / d Z, so every source is comparable.
`zstep=pygranso` selects it; `pip install -e '.[pygranso]'` installs it.
"""
import contextlib
import importlib
import io
import sys
import types
import warnings
from typing import NamedTuple

import numpy as np

from core.jobs import UserError
from core.rollout import b_i, ego_xy, rollout
from planner.qp import SolverFailure

TERMINATION = {  # PyGranso's soln.termination_code, in its own words (pygranso.pygranso docstring)
    0: "converged: stationarity <= opt_tol, feasible to tolerance",
    1: "relative decrease <= rel_tol, feasible to tolerance",
    2: "objective target reached",
    3: "halted by halt_log_fn",
    4: "max iterations (maxit)",
    5: "clock limit (maxclocktime)",
    6: "line search bracketed a minimizer, Wolfe failed at a feasible point",
    7: "line search bracketed a minimizer, Wolfe failed at an infeasible point",
    8: "line search failed to bracket a minimizer",
    9: "no descent direction",
    11: "user function raised",
    12: "QP solver error aborted steering",
    13: "unknown error",
}


class PyGransoSettings(NamedTuple):
    """PyGranso's limits and tolerances per Z-update: iterations, stationarity, violation (m^2 or state units), clock (s);
    the values live in conf/zstep/pygranso.yaml."""

    maxit: int
    opt_tol: float
    viol_ineq_tol: float
    mu0: float  # initial penalty weight on the objective
    limited_mem_size: int  # 0: full BFGS inverse Hessian (the paper's BFGS-SQP); > 0: L-BFGS memory
    maxclocktime: float  # s
    warm_hessian: bool  # carry the BFGS inverse Hessian and mu across the ADMM iterations of one MPC step
    infeasible_tol: float  # max violation (m^2) at which the Z-update counts as infeasible, like sqp's slack_tol


@contextlib.contextmanager
def _pygranso_1_2_compat():
    """What pygranso 1.2.0 needs at import only: `gurobipy` (used for QPsolver='gurobi' alone), tkinter's messagebox
    (an unused import) and numpy's `Inf` (gone in numpy 2). Stand-ins for the missing ones live only for the import.
    """
    import numpy._core.numeric as numeric

    stubs = {"gurobipy": types.SimpleNamespace(GRB=None), "tkinter.messagebox": types.SimpleNamespace(NO="no")}
    stubs = {name: stub for name, stub in stubs.items() if not _importable(name)}
    stub_inf = not hasattr(numeric, "Inf")  # pygransoOptions imports it from numpy.core.numeric
    sys.modules.update(stubs)
    if stub_inf:
        numeric.Inf = np.inf
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # numpy.core.* paths in pygranso
            yield
    finally:
        for name in stubs:
            sys.modules.pop(name, None)
        if stub_inf:
            del numeric.Inf


def _importable(name):
    """Whether `import name` works here (tkinter is present on many Pythons without the Tk library it loads)."""
    try:
        importlib.import_module(name)
        return True
    except ImportError:
        return False


def import_pygranso():
    """PyGranso's solver and its option struct; one UserError naming the extra when it is not installed."""
    try:
        with _pygranso_1_2_compat():
            from pygranso.pygranso import pygranso
            from pygranso.pygransoStruct import pygransoStruct
    except ModuleNotFoundError as e:
        if (e.name or "").split(".")[0] != "pygranso":
            raise
        raise UserError("zstep=pygranso needs PyGranso, which is not installed; run pip install -e '.[pygranso]'") from None
    return pygranso, pygransoStruct


def linear_term(Phi_3, C, rho, mu, c_Z):
    """q with Phi_3 + mu'CZ + rho/2 ||CZ - c_Z||^2 = 1/2 Z'(P_3 + rho C'C)Z + q'Z + const."""
    return Phi_3.q + C.T @ (mu - rho * c_Z)


def source_b(safety):
    """b_i(Z) (N*T_p,) in m^2 as a torch function whose backward is the gradient source's d b_i / d Z."""
    import torch

    last = [None]  # the last linearisation: PyGranso asks for d b_i / d Z once per constraint at the same Z

    class SourceB(torch.autograd.Function):
        @staticmethod
        def forward(ctx, Z):
            ctx.save_for_backward(Z)
            return torch.from_numpy(safety(Z.detach().numpy()))

        @staticmethod
        def backward(ctx, grad):
            (Z,) = ctx.saved_tensors
            _, Jb, last[0] = safety.linearize(Z.numpy(), last[0])
            return grad @ torch.from_numpy(Jb)

    return SourceB.apply


def autodiff_b(safety, source):
    """b_i(Z) (N*T_p,) in m^2 through the predictor's own torch rollout (`source.module` in `source.dtype`): PyGranso
    back-propagates through the network."""
    import torch

    module = source.module
    weights = {k: v.detach() for k, v in module.named_parameters()}  # the network is fixed: no parameter gradients
    phi = lambda w: torch.func.functional_call(module, weights, (w,))
    history = torch.as_tensor(safety.history, dtype=source.dtype)[None]

    def b(Z):
        ego = ego_xy(Z, safety.T_p)[None].to(source.dtype)
        return b_i(rollout(phi, history, ego)[0].double(), safety.R, safety.stretch, safety.p).reshape(-1)

    return b


class PyGransoInfo(NamedTuple):
    """How a PyGranso Z-update ended: its termination code and reason, iterations, function evaluations, the largest
    violation (m^2), whether that counts as infeasible, min b_i (m^2); lin_offset 0: no linearisation to restart."""

    termination: int
    termination_reason: str
    pygranso_iters: int
    fn_evals: int
    slack: float
    infeasible: bool
    b_min: float
    lin_offset: float = 0.0


class PyGransoZStep:
    """argmin_Z Phi_3(Z) + mu'CZ + rho/2||CZ - c_Z||^2 s.t. -b_i(Z) <= 0 and the box, by PyGranso's BFGS-SQP."""

    name = "pygranso"

    def __init__(self, prob, safety, settings: PyGransoSettings):
        """prob: the step's planner.admm.Problem; safety: its planner.safety.Safety."""
        import torch

        self.pygranso, self.Struct = import_pygranso()
        self.torch, self.Phi_3, self.C, self.rho, self.safety, self.s = torch, prob.Phi_3, prob.dyn.C, prob.rho, safety, settings
        self.lo, self.hi = prob.z_lo, prob.z_hi
        self.H = torch.as_tensor(self.Phi_3.P + self.rho * self.C.T @ self.C)  # the smooth part's exact Hessian
        self.i_lo, self.i_hi = np.flatnonzero(np.isfinite(self.lo)), np.flatnonzero(np.isfinite(self.hi))
        self.b = autodiff_b(safety, safety.source) if safety.source.torch_rollout else source_b(safety)
        self.carried = None  # (BFGS state, mu) between the Z-updates of one ADMM solve

    def kernel(self):
        """The Z-update planner.admm's loop calls (planner.zstep.z_update): this Z-step's `update`."""
        return self

    def update(self, cold, lin, Z, mu, c_Z, radius, fresh):
        """planner.zstep.sqp_update's arguments and results: Z_{k+1} by PyGranso, its BFGS state carried between the
        calls of one solve (fresh: afresh); cold, lin and radius are the SQP's and passed through."""
        Z, self.carried, info = self(Z, mu, c_Z, None if fresh else self.carried)
        return Z, radius, lin, info, 1

    def c(self, Z):
        """Inequality constraints c(Z) <= 0: -b_i(Z) (m^2), then z_min - Z and Z - z_max on the finite bounds."""
        torch = self.torch
        return torch.cat([-self.b(Z), torch.from_numpy(self.lo[self.i_lo]) - Z[self.i_lo],
                          Z[self.i_hi] - torch.from_numpy(self.hi[self.i_hi])])

    def options(self, Z, zstate):
        """PyGranso's options: quiet, double precision, warm start at Z (and the carried BFGS state and mu)."""
        opts = self.Struct()
        opts.x0 = self.torch.as_tensor(Z).reshape(-1, 1)
        opts.print_level = 0
        opts.quadprog_info_msg = False
        opts.maxit, opts.opt_tol, opts.viol_ineq_tol = self.s.maxit, self.s.opt_tol, self.s.viol_ineq_tol
        opts.limited_mem_size, opts.maxclocktime, opts.mu0 = self.s.limited_mem_size, self.s.maxclocktime, self.s.mu0
        if self.s.warm_hessian and zstate is not None:
            H, opts.mu0 = zstate
            if self.s.limited_mem_size:
                opts.limited_mem_warm_start = H
            elif H is not None:
                opts.H0, opts.scaleH0 = H, False  # a learned H0 is already scaled; PyGranso scales only the identity
        return opts

    def kept(self, H):
        """The BFGS state to warm-start the next Z-update: L-BFGS as is; a full inverse Hessian only if numerically PD."""
        if self.s.limited_mem_size:
            return H
        H = 0.5 * (H + H.T)
        return H if self.torch.linalg.cholesky_ex(H).info == 0 else None  # PyGranso rejects an H0 that is not PD

    def __call__(self, Z, mu, c_Z, zstate=None):
        """Z_{k+1} from Z_k; zstate is (BFGS state, mu); info: PyGranso's termination code and reason, iterations, b_min."""
        torch = self.torch
        lin_q = torch.as_tensor(linear_term(self.Phi_3, self.C, self.rho, mu, c_Z))
        H, Struct = self.H, self.Struct

        def combined(X):
            ci = Struct()
            ci.c = self.c(X.Z)
            return 0.5 * X.Z @ (H @ X.Z) + lin_q @ X.Z, ci, None

        Z0 = np.clip(Z, self.lo, self.hi)
        printed = io.StringIO()
        try:
            with contextlib.redirect_stdout(printed), warnings.catch_warnings():  # OSQP 1.x prints per polish,
                warnings.simplefilter("ignore", PendingDeprecationWarning)  # and warns per solve() PyGranso makes
                soln = self.pygranso(var_spec={"Z": [len(Z0)]}, combined_fn=combined,
                                     user_opts=self.options(Z0, zstate))
        except SystemExit:  # PyGranso exits when the functions fail at x0 (e.g. non-finite values)
            lines = [ln for ln in printed.getvalue().splitlines() if ln.strip() and not ln.startswith(" ")]
            raise SolverFailure(f"PyGranso stopped the process: {' / '.join(lines[-2:])}") from None
        point = getattr(soln, "best", None) or soln.most_feasible  # best feasible to tolerance, else least violating
        Z_new = point.x.detach().reshape(-1).numpy().astype(float)
        b = self.safety(Z_new)
        violation = float(max(-b.min(initial=np.inf), np.max(self.lo - Z_new), np.max(Z_new - self.hi), 0.0))
        code = int(soln.termination_code)
        info = PyGransoInfo(code, f"pygranso {code}: {TERMINATION.get(code, 'unknown')}", int(soln.iters),
                            int(soln.fn_evals), violation, violation > self.s.infeasible_tol, float(b.min(initial=np.inf)))
        return Z_new, (self.kept(soln.H_final), float(soln.final.mu)), info
