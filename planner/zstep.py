"""Z-update solvers behind one signature, chosen by the `zstep` config group (conf/zstep/); `sqp` is sequential QP with OSQP.

A Z-step is built once per MPC step from (problem, safety, OSQP settings), the problem a planner.admm.Problem (its
Phi_3, C, rho and state box), and called per ADMM iteration as zstep(Z_k, mu, c_Z, zstate) -> (Z_{k+1}, zstate, info),
where zstate is the solver's own carried state (None at first, and whenever ADMM wants it to start afresh). Its class
attribute `name` is the option's name (MLflow param `zstep`). An info key `lin_offset` (m) says how far Z_{k+1} lies from where b_i was last
linearised (see planner.admm.admm_solve).
"""
from functools import lru_cache
from typing import NamedTuple

import numpy as np
from scipy import sparse

from planner.qp import QP


class TrustRegion(NamedTuple):
    """The trust-region test of an SQP step on the merit function (Nocedal and Wright's Algorithm 4.1), one set of
    constants for both cores: a step is accepted when its actual decrease is at least `accept` times the predicted one
    (or the prediction is below `flat`: nothing left to gain); after one with at least `good` times it that reached
    `full` times the radius, the radius grows `grow` times; a rejected step shrinks it `shrink` times."""

    accept: float
    good: float
    full: float
    grow: float
    shrink: float
    flat: float


TRUST_REGION = TrustRegion(accept=0.1, good=0.75, full=0.99, grow=2.0, shrink=0.5, flat=1e-12)


def verdict(actual, predicted, step, radius, tr: TrustRegion, min_radius, max_radius):
    """The trust-region test of a step of size `step` (inf-norm, m) at radius `radius` (m): (accepted, next radius)."""
    if actual >= tr.accept * predicted or predicted <= tr.flat:
        if actual >= tr.good * predicted and step >= tr.full * radius:
            radius = min(tr.grow * radius, max_radius)
        return True, radius
    return False, max(tr.shrink * radius, min_radius)


class ZState(NamedTuple):
    """What the SQP Z-step carries from one ADMM iteration to the next (ADMMState.zstate; None: start afresh, the
    radius reset and b_i linearised anew): its trust radius (m) and b_i's linearisation (planner.safety.Safety's)."""

    radius: float
    lin: tuple


class SQPSettings(NamedTuple):
    """Trust region on the ego's x, y (m), its bounds and growth, iteration cap, step tolerance (m), safety form; the
    values live in conf/zstep/sqp.yaml."""

    max_iters: int
    trust_radius: float
    min_radius: float
    max_radius: float
    tol: float
    mode: str  # hard: b_i >= 0 with an elastic slack; penalty: - lambda_s' b_i in the objective (eq. (11))
    lambda_s: float  # penalty-form multiplier (1/m^2 per constraint)
    slack_penalty: float  # L1 price of violating a linearised b_i >= 0 (per m^2)
    slack_tol: float  # slack (m^2) above which the linearisation counts as infeasible
    reuse_radius: float  # m: b_i's linearisation is reused while the ego's planned xy stay this close to where it was taken
    trust_region: TrustRegion = TRUST_REGION  # the step test's constants, not a tuning knob


@lru_cache(maxsize=8)
def constraint_pattern(n_Z, n_b):
    """G = [I 0; mask I; 0 I] over x = [Z; s] (CSC, sorted), its (row, col, data) triplets, where the d b_i / d Z values
    go, and which Z entries the trust region bounds (the ego's x, y); fixed per (n_Z, n_b), so built once."""
    # b_i at step t depends on the ego's x, y at steps <= t: that lower-triangular block pattern is fixed.
    T_p = n_Z // 4
    t_row = np.repeat(np.arange(T_p)[None], n_b // T_p, 0).reshape(-1)
    t_col, k_col = np.arange(n_Z) // 4, np.arange(n_Z) % 4
    mask = (t_col[None] <= t_row[:, None]) & (k_col[None] < 2)
    G = sparse.bmat([[sparse.eye(n_Z), None], [sparse.csc_matrix(mask.astype(float)), sparse.eye(n_b)],
                     [None, sparse.eye(n_b)]], format="csc")
    G.sort_indices()
    cols = np.repeat(np.arange(G.shape[1]), np.diff(G.indptr))
    is_b = (G.indices >= n_Z) & (G.indices < n_Z + n_b) & (cols < n_Z)
    return G, G.indices, cols, G.data.copy(), is_b, np.tile([True, True, False, False], T_p)


class SQPZStep:
    """argmin_Z Phi_3(Z) + mu'CZ + rho/2||CZ - c_Z||^2 s.t. box, b_i(Z) >= 0, by trust-region SQP over x = [Z; s]."""

    name = "sqp"

    def __init__(self, prob, safety, osqp_settings, settings: SQPSettings):
        self.Phi_3, self.C, self.rho, self.safety, self.s = prob.Phi_3, prob.dyn.C, prob.rho, safety, settings
        self.lo, self.hi = prob.z_lo, prob.z_hi
        n_Z = self.C.shape[0]
        n_b = safety.rows
        self.n_Z, self.n_b = n_Z, n_b
        self.H = self.Phi_3.P + self.rho * (self.C.T @ self.C)  # the exact Hessian of the smooth part
        G, self.G_rows, self.G_cols, G_data, self.is_b, self.xy = constraint_pattern(n_Z, n_b)
        # the slack in units of 1/sqrt(its price): its column and its price alike ~sqrt(slack_penalty), which OSQP's
        # equilibration handles; unscaled, its multipliers ~slack_penalty took OSQP ~5x more iterations
        self.k_s = settings.slack_penalty ** -0.5
        self.G_data = np.where((self.G_cols >= n_Z) & (self.G_rows < n_Z + n_b), self.k_s, G_data)
        G = sparse.csc_matrix((self.G_data, G.indices, G.indptr), shape=G.shape)
        self.qp = QP(self.P(), np.zeros(n_Z + n_b), G, np.zeros(G.shape[0]), np.full(G.shape[0], np.inf), osqp_settings)

    def P(self):
        """The QP's Hessian over x = [Z; s]: H, and nothing on the slack (priced linearly)."""
        P = np.zeros((self.n_Z + self.n_b,) * 2)
        P[:self.n_Z, :self.n_Z] = self.H
        return P

    def model(self, Z, lin_q):
        """The exact quadratic part 1/2 Z'HZ + lin_q'Z."""
        return 0.5 * Z @ (self.H @ Z) + lin_q @ Z

    def merit(self, Z, lin_q, b):
        """Quadratic part plus the safety term: L1 violation price (hard) or - lambda_s sum b_i (penalty)."""
        if self.s.mode == "hard":
            return self.model(Z, lin_q) + self.s.slack_penalty * np.sum(np.maximum(0.0, -b))
        return self.model(Z, lin_q) - self.s.lambda_s * np.sum(b)

    def __call__(self, Z, mu, c_Z, zstate: ZState | None = None):
        """Z_{k+1} from Z_k and the Z-step's next ZState; info: SQP iterations, max slack, infeasible, min b_i,
        lin_offset (m)."""
        radius, lin = (self.s.trust_radius, None) if zstate is None else zstate
        reuse = 0.0 if zstate is None else self.s.reuse_radius
        lin_q = self.Phi_3.q + self.C.T @ (mu - self.rho * c_Z)
        Z = np.clip(Z, self.lo, self.hi)
        b, Jb, lin = self.safety.linearize(Z, lin, reuse)
        b_Z, slack, its = b, 0.0, 0
        for its in range(1, self.s.max_iters + 1):
            q = np.concatenate([lin_q, np.full(self.n_b, self.s.slack_penalty * self.k_s)])
            if self.s.mode == "penalty":
                q[:self.n_Z] -= self.s.lambda_s * Jb.sum(0)
            tr = np.where(self.xy, radius, np.inf)
            b_lo = Jb @ Z - b if self.s.mode == "hard" else np.full(self.n_b, -np.inf)
            l = np.concatenate([np.maximum(self.lo, Z - tr), b_lo, np.zeros(self.n_b)])
            u = np.concatenate([np.minimum(self.hi, Z + tr), np.full(2 * self.n_b, np.inf)])
            data = self.G_data.copy()
            data[self.is_b] = Jb[self.G_rows[self.is_b] - self.n_Z, self.G_cols[self.is_b]]
            x = self.qp.solve(q=q, l=l, u=u, Gx=data)
            Z_new, s = np.clip(x[:self.n_Z], self.lo, self.hi), x[self.n_Z:] * self.k_s  # OSQP's box is met to its tolerance
            slack = float(max(s.max(initial=0.0), 0.0))
            b_new, lin = self.safety.trial(Z_new, lin, self.s.reuse_radius)
            here = self.merit(Z, lin_q, b)
            predicted = here - self.merit(Z_new, lin_q, b + Jb @ (Z_new - Z))
            actual = here - self.merit(Z_new, lin_q, b_new)
            step = float(np.max(np.abs(Z_new - Z)))
            accepted, radius = verdict(actual, predicted, step, radius, self.s.trust_region, self.s.min_radius,
                                       self.s.max_radius)
            if accepted:
                Z, b_Z = Z_new, b_new
                if step < self.s.tol:
                    break
                b, Jb, lin = self.safety.linearize(Z, lin, self.s.reuse_radius)
        return Z, ZState(radius, lin), {"sqp_iters": its, "slack": slack, "infeasible": slack > self.s.slack_tol,
                                        "b_min": float(b_Z[:self.safety.n_b].min(initial=np.inf)),
                                        "c_min": float(b_Z[self.safety.n_b:].min(initial=np.inf)),
                                        "lin_offset": self.safety.offset(Z, lin)}
