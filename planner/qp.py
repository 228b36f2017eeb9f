"""The one place OSQP is called: set a convex QP up once, then update vectors (and constraint values) and re-solve."""
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
        self.solver = osqp.OSQP()
        self.solver.setup(sparse.triu(sparse.csc_matrix(P), format="csc"), np.asarray(q, float), self.G,
                          np.asarray(l, float), np.asarray(u, float), verbose=False, warm_starting=True, **settings)

    def solve(self, q=None, l=None, u=None, Gx=None):
        """Optimal x after updating any of q, l, u and the constraint matrix values Gx (same sparsity, CSC order)."""
        vectors = {k: np.asarray(v, float) for k, v in (("q", q), ("l", l), ("u", u)) if v is not None}
        if vectors:
            self.solver.update(**vectors)
        if Gx is not None:
            self.solver.update(Ax=np.asarray(Gx, float))
        result = self.solver.solve(raise_error=False)
        if result.info.status not in ACCEPTED or not np.all(np.isfinite(result.x)):
            raise SolverFailure(f"OSQP {result.info.status}")
        return result.x
