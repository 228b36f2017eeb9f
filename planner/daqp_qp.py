"""The one place DAQP (a dual active-set solver for small dense QPs) is called, by the compiled core (mpc.core=compiled):
the Delta- and alpha-update box QPs when their closed-form minimiser leaves the box, and the Z-step's QPs with b_i's
linearisation as soft constraints priced by an L1 penalty, warm-started across one MPC step."""
import daqp
import numpy as np

from planner.qp import SolverFailure

INF = 1e30  # DAQP's infinity: bounds at or beyond it are absent
SOFT_RHO = 1e6  # DAQP's reciprocal quadratic weight on a soft violation s: s^2 / (2 SOFT_RHO) is negligible beside the L1 price


def optimal(x, exitflag):
    """x if DAQP found an optimum (1; 2: with soft constraints violated), else SolverFailure naming its exit flag."""
    if exitflag < 1 or not np.isfinite(x @ x):
        raise SolverFailure(f"DAQP exit flag {exitflag}")
    return x


class DaqpBox:
    """min 1/2 x'Px + q'x on the box of a planner.qp.BoxQP (its P, P^-1 and bounds kept here for the closed-form
    kernels) by DAQP, set up at its first solve and warm-started from the last active set."""

    def __init__(self, qp):
        self.P, self.P_inv, self.lo, self.hi = qp.P, qp.P_inv, qp.lo, qp.hi
        self.model = None

    def solve(self, q):
        """The box QP's minimiser for linear term q by DAQP."""
        if self.model is None:
            self.model = daqp.Model()
            self.model.setup(self.P, q, np.zeros((0, len(q))), self.hi, self.lo)
        else:
            self.model.update(f=q)
        x, _, flag, _ = self.model.solve()
        return optimal(x, flag)


class SoftQP:
    """min 1/2 x'Hx + f'x + price sum max(0, c_lo - Ax) s.t. lo <= x <= hi, H fixed; set up at its first solve, then
    updated and warm-started from the last active set; A has `rows` rows. `soft` False: they are hard (c_lo may be -INF)."""

    def __init__(self, H, price: float, soft: bool, rows: int):
        self.H, self.price, self.soft = np.ascontiguousarray(H), price, soft
        self.bu = np.full(len(H) + rows, INF)  # [box; rows]: the rows' upper bounds stay absent
        self.bl = np.empty(len(H) + rows)
        self.model = None

    def solve(self, f, lo, hi, A, c_lo):
        """The minimiser x for this linear term, box lo, hi (n,) and rows c_lo <= Ax (metres, m^2)."""
        n = len(f)
        self.bu[:n], self.bl[:n], self.bl[n:] = hi, lo, c_lo
        if self.model is None:
            m = len(self.bu)
            sense = np.concatenate([np.zeros(n), np.full(len(A), 8 if self.soft else 0)]).astype(np.int32)
            self.model = daqp.Model()
            self.model.setup(self.H, f, A, self.bu, self.bl, sense)
            weights = np.full(m, SOFT_RHO)
            self.model.soft_weights(rho_l=weights, rho_u=weights, w_l=np.full(m, self.price), w_u=np.full(m, self.price))
        else:
            self.model.update(f=f, A=A, bupper=self.bu, blower=self.bl)
        x, _, flag, _ = self.model.solve()
        return optimal(x, flag)
