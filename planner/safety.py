"""Eq. (6)-(8) for one MPC step: b_i(Z) >= 0 against the gradient source's predictions, linearised with its Jacobian."""
import numpy as np

from core.rollout import b_i, b_i_jacobian, ego_xy


class Safety:
    """b_i(Z) for one MPC step: the gradient source's predictions from `history`, radius R (m); caches the last linearisation."""

    def __init__(self, source, history, R, T_p):
        self.source, self.history, self.R, self.T_p = source, np.asarray(history, dtype=float), R, T_p
        self._last = (None, None)

    def ego_xy(self, Z):
        """The ego's planned xy (T_p, 2) from Z stacked as [x, y, psi, v] per step."""
        return ego_xy(Z, self.T_p)

    def __call__(self, Z):
        """b_i(Z) flattened (N*T_p,), m^2, from the predictor's values only."""
        return b_i(self.source.values(self.history, self.ego_xy(Z)[None])[0], self.R).reshape(-1)

    def trial(self, Z):
        """b_i(Z) at a trial step: for a source whose values come with the Jacobian at little extra cost (`joint`), from
        the linearisation at Z, cached, since an accepted step is linearised next; else as __call__."""
        return self.linearize(Z)[0] if getattr(self.source, "joint", False) else self(Z)

    def linearize(self, Z):
        """b_i(Z) (N*T_p,) and d b_i / d Z (N*T_p, 4T_p) from the gradient source."""
        key = np.asarray(Z, dtype=float).tobytes()
        if self._last[0] != key:
            values, grads = self.source.jacobian(self.history, self.ego_xy(Z))
            self._last = (key, b_i_jacobian(values, grads, self.R))
        return self._last[1]
