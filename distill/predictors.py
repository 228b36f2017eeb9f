"""The predictor interface and the non-interactive baseline: constant velocity."""
import numpy as np


class ConstantVelocity:
    """phi(window) = last xy + (last xy - previous xy): every car keeps its last displacement (m per step)."""

    name = "cv"

    def phi(self, window):
        """Next xy (B, SLOTS, 2) from window (B, T_obs, SLOTS, 2), metres."""
        return 2.0 * window[:, -1] - window[:, -2]

    def phi_jac(self, window):
        """Next xy (B, SLOTS, 2) and its exact local Jacobian (B, SLOTS*2, T_obs*SLOTS*2)."""
        b, t_obs, m, _ = window.shape
        J = np.zeros((m * 2, t_obs, m * 2))
        J[:, -1] = 2.0 * np.eye(m * 2)
        J[:, -2] = -np.eye(m * 2)
        return self.phi(np.asarray(window, dtype=float)), np.broadcast_to(J.reshape(1, m * 2, t_obs * m * 2), (b, m * 2, t_obs * m * 2))
