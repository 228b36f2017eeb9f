"""The planner's view of the surrogate: `load()` -> local Jacobians (and fused next xy) from models/surrogate.onnx."""
from pathlib import Path

import numpy as np
import onnx
from onnx.utils import Extractor

from core.jobs import MissingModel, UserError, model_file, recover
from distill.export import onnx_session
from distill.models import check_finite, probe_window


class Surrogate:
    """An onnxruntime session: `.jac(window)` -> J (B, SLOTS*2, T_obs*SLOTS*2) m/m float64, `.source` its teacher and
    `.source_sha256` the sha256 of the checkpoint it learned ("": not recorded); a fused export also `.phi(window)`, the
    source's next xy, each from its own half of the graph (`halves`)."""

    def __init__(self, session, source, path, halves=None, source_sha256=""):
        self.session, self.source, self.path, self.source_sha256 = session, source, path, source_sha256
        self.name = "surrogate"
        self.fused = "next" in [o.name for o in session.get_outputs()]
        self.halves = halves or {"J": session}  # output name -> the session that computes it alone

    def jac(self, window):
        """Learned local Jacobian J (B, SLOTS*2, T_obs*SLOTS*2), float64, of window (B, T_obs, SLOTS, 2) metres."""
        (J,) = self.halves["J"].run(["J"], {"window": np.asarray(window, dtype=np.float32)})
        return J.astype(np.float64)

    def phi(self, window):
        """The source predictor's next xy (B, SLOTS, 2) m of window (B, T_obs, SLOTS, 2) m, without J; fused models only."""
        if not self.fused:
            raise UserError(f"{self.path} was exported without the source's forward pass (surrogate fused=false)")
        (nxt,) = self.halves["next"].run(["next"], {"window": np.asarray(window, dtype=np.float32)})
        return nxt.astype(np.float64)

    def phi_jac(self, window):
        """(next xy (B, SLOTS, 2) m from the source predictor, J (B, SLOTS*2, T_obs*SLOTS*2)) in one call; fused models only."""
        if not self.fused:
            raise UserError(f"{self.path} was exported without the source's forward pass (surrogate fused=false)")
        J, nxt = self.session.run(["J", "next"], {"window": np.asarray(window, dtype=np.float32)})
        return nxt.astype(np.float64), J.astype(np.float64)


def halves(path, advice) -> dict:
    """{output name: a session on the part of the fused graph at `path` that computes it}: onnxruntime runs every node of
    a graph whatever outputs a call asks for, so values alone (a safeguard check, a rollout's recursion) would pay for J
    and a batch of J for the source's forward pass."""
    extract = Extractor(onnx.load(str(path))).extract_model
    return {out: onnx_session(path, advice, extract(["window"], [out]).SerializeToString()) for out in ("next", "J")}


def load(models_dir, T_obs, n_slots):
    """The surrogate from <models_dir>/surrogate.onnx, checked against window (B, T_obs, M, 2) -> J (B, M*2, T_obs*M*2),
    M = n_slots + 1 (the ego and the other cars it sees), and finite on a probe window."""
    M = n_slots + 1
    recover(models_dir)  # a model a stopped job committed but did not finish moving in
    path = Path(models_dir) / "surrogate.onnx"
    if not path.exists():
        raise MissingModel(f"{path} not found: run `surrogate`")
    expected = f"expected window (B, {T_obs}, {M}, 2) -> J (B, {2 * M}, {2 * T_obs * M})"
    session = onnx_session(model_file(path), f"{expected}; re-run `surrogate`")
    inputs = {i.name: i.shape[1:] for i in session.get_inputs()}
    outputs = {o.name: o.shape[1:] for o in session.get_outputs()}
    if inputs != {"window": [T_obs, M, 2]} or outputs.get("J") != [2 * M, 2 * T_obs * M] or \
            outputs.get("next", [M, 2]) != [M, 2]:
        raise UserError(f"{path} has inputs {inputs} and outputs {outputs}; {expected}; re-run `surrogate`")
    meta = session.get_modelmeta().custom_metadata_map
    source = meta.get("source")
    if not source:
        raise UserError(f"{path} does not record the predictor it learned (ONNX metadata `source`); re-run `surrogate`")
    surrogate = Surrogate(session, source, path, halves(path, f"{expected}; re-run `surrogate`") if "next" in outputs else None,
                          meta.get("source_sha256", ""))
    window = probe_window(T_obs, M)
    check_finite(surrogate.phi_jac(window) if surrogate.fused else (surrogate.jac(window),), path, "re-run `surrogate`")
    return surrogate
