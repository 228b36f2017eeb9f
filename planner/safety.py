"""Eq. (6)-(8) for one MPC step: b_i(Z) >= 0 against the gradient source's predictions, linearised with its Jacobian,
and optionally the courtesy rows c_i(Z) = a_i + b_c >= 0: nobody predicted to brake harder than b_c under the plan."""
import numpy as np

from core.rollout import accelerations, b_i, b_i_jacobian, courtesy_jacobian, ego_xy


def values(source, history, ego):
    """The predictor's rollout values (T_p, SLOTS, 2) under one ego plan's xy (T_p, 2), from the source's own rollout."""
    return source.values(history, ego[None])[0]


class Safety:
    """The constraint rows of one MPC step, b_i(Z) (N*T_p, m^2) then, with `courtesy` = (dt s, b_c m/s^2), c_i(Z)
    (N*T_p, m/s^2): the gradient source's predictions from `history`, radius R (m) across the road and stretch * R
    along it, shape exponent p (core.rollout.b_i). A linearisation (the ego plan it was taken at, the rollout values and
    their derivative) is returned to the caller, who carries it (the Z-step, in ADMM's state) for nearby plans to reuse."""

    def __init__(self, source, history, R, T_p, courtesy=None, stretch=1.0, p=2.0):
        self.source, self.history, self.R, self.T_p = source, np.asarray(history, dtype=float), R, T_p
        self.stretch, self.p = stretch, p
        self.courtesy = courtesy
        self.n_b = (self.history.shape[1] - 1) * T_p  # b_i rows; the courtesy rows follow
        self.rows = self.n_b * (2 if courtesy else 1)
        self.jacobian = source.jacobian  # (history, ego xy) -> (values, d values / d ego xy)

    def ego_xy(self, Z):
        """The ego's planned xy (T_p, 2) from Z stacked as [x, y, psi, v] per step."""
        return ego_xy(Z, self.T_p)

    def __call__(self, Z):
        """The rows at Z (b_i flattened, then the courtesy rows), from the predictor's values only."""
        values = self.source.values(self.history, self.ego_xy(Z)[None])[0]
        b = b_i(values, self.R, self.stretch, self.p).reshape(-1)
        if not self.courtesy:
            return b
        dt, b_c = self.courtesy
        return np.concatenate([b, (accelerations(values, self.history, dt) + b_c).reshape(-1)])

    def offset(self, Z, lin):
        """How far (m, largest over the horizon and x, y) the ego's planned xy in Z lie from the linearisation lin's."""
        return np.inf if lin is None else float(np.max(np.abs(self.ego_xy(Z) - lin[0])))

    def reused(self, Z, lin):
        """b_i(Z) and d b_i / d Z with the others' predictions affine in the ego plan about the linearisation lin: the
        ego's own position enters b_i exactly, only the others' response is linearised."""
        ego0, values0, grads = lin
        values = values0 + np.einsum("tmkse,se->tmk", grads, self.ego_xy(Z) - ego0)  # the ego slot moves exactly with Z
        b, Jb = b_i_jacobian(values, grads, self.R, self.stretch, self.p)
        if not self.courtesy:
            return b, Jb
        c, Jc = courtesy_jacobian(values, grads, self.history, *self.courtesy)
        return np.concatenate([b, c]), np.concatenate([Jb, Jc])

    def trial(self, Z, lin, reuse_radius=0.0):
        """(b_i(Z) at a trial step, the linearisation now): within reuse_radius of lin, from it; for a source whose
        values come with the Jacobian at little extra cost (`joint`), from a linearisation at Z, kept since an accepted
        step is linearised next; else as __call__."""
        if self.offset(Z, lin) <= reuse_radius or self.source.joint:
            b, _, lin = self.linearize(Z, lin, reuse_radius)
            return b, lin
        return self(Z), lin

    def linearize(self, Z, lin=None, reuse_radius=0.0):
        """The rows at Z (rows,), their derivative d / d Z (rows, 4T_p) and the linearisation they come from: lin while
        the ego's plan stays within reuse_radius (m) of where it was taken (0: only at the same plan), else a new one
        from the gradient source (None: none yet)."""
        if self.offset(Z, lin) > reuse_radius:
            ego = self.ego_xy(Z).copy()
            lin = (ego, *self.jacobian(self.history, ego))
        return (*self.reused(Z, lin), lin)
