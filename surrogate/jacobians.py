"""Training targets: the source predictor's local Jacobian d phi(window) / d window on dataset and planner windows.

J has shape (B, SLOTS*2, T_obs*SLOTS*2): rows are next xy flattened (M, 2), columns the window flattened (T_obs, SLOTS, 2),
both C-order, metres per metre; the layout `core.rollout.rollout_jacobian` composes.
"""
import numpy as np

from core.rollout import rollout


def chunks(a, size):
    """Consecutive slices of `a` of at most `size` rows."""
    return [a[i:i + size] for i in range(0, len(a), size)]


def autodiff(predictor, windows, batch=1024):
    """Exact J (B, SLOTS*2, T_obs*SLOTS*2) float64 from the predictor's own phi_jac (torch.func.jacrev for torch networks)."""
    return np.concatenate([predictor.phi_jac(w)[1] for w in chunks(np.asarray(windows), batch)])


def central(phi, windows, h, batch=64):
    """J (B, SLOTS*2, T_obs*SLOTS*2) float64 by central differences of a black-box numpy phi, step h (m) per input."""
    windows = np.asarray(windows, dtype=np.float64)
    shape = windows.shape[1:]
    n_in = int(np.prod(shape))
    steps = h * np.eye(n_in).reshape((n_in,) + shape)
    out = []
    for chunk in chunks(windows, batch):
        probes = np.concatenate([chunk[:, None] + steps[None], chunk[:, None] - steps[None]], axis=1)
        nxt = np.asarray(phi(probes.reshape((-1,) + shape)), dtype=np.float64).reshape(len(chunk), 2, n_in, -1)
        out.append(((nxt[:, 0] - nxt[:, 1]) / (2.0 * h)).transpose(0, 2, 1))
    return np.concatenate(out)


def planner_windows(phi, history, ego_future):
    """Every window the Remark 2 recursion visits (B*T_p, T_obs, SLOTS, 2) when the ego follows `ego_future` (B, T_p, 2)."""
    track = np.concatenate([history, rollout(phi, history, ego_future)], axis=1)  # (B, T_obs + T_p, SLOTS, 2)
    t_obs, t_p = history.shape[1], ego_future.shape[1]
    return np.stack([track[:, tau:tau + t_obs] for tau in range(t_p)], axis=1).reshape((-1,) + history.shape[1:])
