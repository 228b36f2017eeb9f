"""The one place OSQP is called: set a convex QP up once, then update vectors (and matrix values) and re-solve; and the
small box QPs of the Delta- and alpha-updates, solved in closed form when the box is inactive."""
import numpy as np
import osqp
from scipy import sparse


class SolverFailure(RuntimeError):
    """OSQP returned no usable solution (infeasible, non-convex, numerical trouble); the MPC step falls back."""


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


class BoxQP:
    """min 1/2 x'Px + q'x s.t. lo <= x <= hi for a small positive definite P, built once, `solve(q)` per iteration.

    First the unconstrained minimiser -P^-1 q (P inverted once per step): inside the box it is the box QP's solution,
    exactly, and costs a matrix-vector product; otherwise OSQP, set up at its first use and warm-started."""

    def __init__(self, P, q, lo, hi, settings: dict):
        self.P = np.asarray(P, float)
        self.q0, self.settings = q, settings
        self.lo, self.hi = np.full(len(self.P), lo, float), np.full(len(self.P), hi, float)
        self.qp = None
        self.P_inv = np.linalg.inv(self.P)  # scipy's cho_factor and cho_solve: 4x the time in argument checks at 8 x 8

    def solve(self, q):
        """The box QP's minimiser for linear term q."""
        x = -(self.P_inv @ q)
        if np.all(x >= self.lo) and np.all(x <= self.hi):
            return x
        if self.qp is None:
            self.qp = QP(self.P, self.q0, sparse.eye(len(self.P), format="csc"), self.lo, self.hi, self.settings)
        return self.qp.solve(q=q)
