"""The planner's view of the surrogate: `load()` -> local Jacobians (and fused next xy) from models/surrogate.onnx, and
whole linearisations from models/surrogate_rollout.onnx where it was exported."""
from pathlib import Path

import numpy as np

from core.jobs import UserError
from distill.export import onnx_session

ROLLOUT = "surrogate_rollout.onnx"


class Surrogate:
    """onnxruntime sessions: `.jac(window)` -> J (B, SLOTS*2, T_obs*SLOTS*2) m/m float64, `.source` its teacher; `.rollout`
    -> a whole linearisation where surrogate_rollout.onnx exists (`.rollout_session` not None)."""

    def __init__(self, session, source, path, rollout_session=None):
        self.session, self.source, self.path, self.rollout_session = session, source, path, rollout_session
        self.name = "surrogate"
        self.fused = "next" in [o.name for o in session.get_outputs()]

    def jac(self, window):
        """Learned local Jacobian J (B, SLOTS*2, T_obs*SLOTS*2), float64, of window (B, T_obs, SLOTS, 2) metres."""
        (J,) = self.session.run(["J"], {"window": np.asarray(window, dtype=np.float32)})
        return J.astype(np.float64)

    def phi_jac(self, window):
        """(next xy (B, SLOTS, 2) m from the source predictor, J (B, SLOTS*2, T_obs*SLOTS*2)) in one call; fused models only."""
        if not self.fused:
            raise UserError(f"{self.path} was exported without the source's forward pass (surrogate fused=false)")
        J, nxt = self.session.run(["J", "next"], {"window": np.asarray(window, dtype=np.float32)})
        return nxt.astype(np.float64), J.astype(np.float64)

    def rollout(self, history, ego_futures, grads=True):
        """The source's rollout values (B, T_p, SLOTS, 2) m of histories (B, T_obs, SLOTS, 2) under ego plans (B, T_p, 2),
        and (grads=True) d values / d ego plan (B, T_p, SLOTS, 2, T_p, 2) from the learned local Jacobians; one call."""
        feeds = {"history": np.asarray(history, dtype=np.float32), "ego_future": np.asarray(ego_futures, dtype=np.float32)}
        out = self.rollout_session.run(["values", "grads"] if grads else ["values"], feeds)
        return tuple(a.astype(np.float64) for a in out) if grads else out[0].astype(np.float64)


def open_checked(path, inputs, outputs, advice):
    """A session on `path` whose inputs and outputs (shapes after the batch axis) are exactly these; a UserError otherwise."""
    expected = ", ".join(f"{k} (B, {', '.join(map(str, v))})" for k, v in {**inputs, **outputs}.items())
    session = onnx_session(path, f"expected {expected}; {advice}")
    got = {i.name: i.shape[1:] for i in [*session.get_inputs(), *session.get_outputs()]}
    if got != {**inputs, **outputs}:
        raise UserError(f"{path} has {got}; expected {expected}; {advice}")
    return session


def load(models_dir="models", T_obs=8, M=5, rollout=False, T_p=8):
    """The surrogate from <models_dir>/surrogate.onnx, checked against window (B, T_obs, SLOTS, 2) -> J (B, SLOTS*2,
    T_obs*SLOTS*2); with rollout, also <models_dir>/surrogate_rollout.onnx, checked for horizon T_p (steps)."""
    path = Path(models_dir) / "surrogate.onnx"
    if not path.exists():
        raise UserError(f"{path} not found: run `surrogate`")
    expected = f"expected window (B, {T_obs}, {M}, 2) -> J (B, {2 * M}, {2 * T_obs * M})"
    session = onnx_session(path, f"{expected}; re-run `surrogate`")
    inputs = {i.name: i.shape[1:] for i in session.get_inputs()}
    outputs = {o.name: o.shape[1:] for o in session.get_outputs()}
    if inputs != {"window": [T_obs, M, 2]} or outputs.get("J") != [2 * M, 2 * T_obs * M] or \
            outputs.get("next", [M, 2]) != [M, 2]:
        raise UserError(f"{path} has inputs {inputs} and outputs {outputs}; {expected}; re-run `surrogate`")
    source = session.get_modelmeta().custom_metadata_map.get("source")
    if not source:
        raise UserError(f"{path} does not record the predictor it learned (ONNX metadata `source`); re-run `surrogate`")
    rollout_session = None
    if rollout:
        rpath = Path(models_dir) / ROLLOUT
        if not rpath.exists():
            raise UserError(f"{rpath} not found: run `surrogate` (or use the per-window path, gradients.rollout=false)")
        rollout_session = open_checked(rpath, {"history": [T_obs, M, 2], "ego_future": [T_p, 2]},
                               {"values": [T_p, M, 2], "grads": [T_p, M, 2, T_p, 2]},
                               f"re-run `surrogate` with paper.T_p={T_p}")
        if rollout_session.get_modelmeta().custom_metadata_map.get("source") != source:
            raise UserError(f"{rpath} and {path} learned different predictors; re-run `surrogate`")
    return Surrogate(session, source, path, rollout_session)
