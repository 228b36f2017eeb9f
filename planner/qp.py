"""The one place OSQP is called (the safeguard's repair, planner.repair): set a convex QP up once, then update vectors
(and matrix values) and re-solve."""
import numpy as np
import osqp
from scipy import sparse


class SolverFailure(RuntimeError):
    """A QP solver (OSQP, DAQP) returned no usable solution (infeasible, non-convex, numerical trouble); the MPC step falls
    back."""


ACCEPTED = ("solved", "solved inaccurate", "maximum iterations reached")


class QP:
    """min 1/2 x'Px + q'x s.t. l <= Gx <= u, built once; `solve(q=, l=, u=, Gx=)` updates and warm-starts."""

    def __init__(self, P, q, G, l, u, settings: dict):
        self.G = sparse.csc_matrix(G)
        P = sparse.csc_matrix(np.triu(P) if isinstance(P, np.ndarray) else sparse.triu(P))
        P.sort_indices()
        self.l, self.u = np.asarray(l, float), np.asarray(u, float)
        self.solver = osqp.OSQP()
        self.solver.setup(P, np.asarray(q, float), self.G, self.l, self.u, verbose=False, warm_starting=True, **settings)

    def solve(self, q=None, l=None, u=None, Gx=None):
        """Optimal x after updating any of q, l, u and the constraint matrix values Gx (same sparsity, CSC order)."""
        data = {k: np.asarray(v, float) for k, v in (("q", q), ("l", l), ("u", u), ("Ax", Gx)) if v is not None}
        lo, hi = data.get("l", self.l), data.get("u", self.u)
        if np.any(lo > hi):  # OSQP would refuse the update with a printed error and re-solve the previous bounds
            raise SolverFailure(f"bounds cross (l > u at {int(np.sum(lo > hi))} rows)")
        self.l, self.u = lo, hi
        if data:
            self.solver.update(**data)
        result = self.solver.solve(raise_error=False)
        if result.info.status not in ACCEPTED or not np.all(np.isfinite(result.x)):
            raise SolverFailure(f"OSQP {result.info.status}")
        return result.x
