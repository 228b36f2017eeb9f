"""ONNX export of a predictor network and an onnxruntime predictor that reads it back (numpy in, numpy out, metres)."""
from pathlib import Path

import numpy as np

from core.jobs import UserError, atomic_file


def export_onnx(module, path: Path, t_obs=8, m=5):
    """Write the torch `module` (window (B, T_obs, SLOTS, 2) -> next (B, SLOTS, 2)) to `path` atomically, batch size dynamic."""
    import torch  # here, not at the top: the planner reads ONNX files through this module without torch

    example = torch.zeros(2, t_obs, m, 2)

    def write(tmp):
        """Export to the temporary path."""
        # the legacy TorchScript exporter: the dynamo one needs onnxscript, which is not a dependency
        torch.onnx.export(module.eval(), (example,), str(tmp), input_names=["window"], output_names=["next"],
                          dynamic_axes={"window": {0: "batch"}, "next": {0: "batch"}}, opset_version=17, dynamo=False)

    atomic_file(Path(path), write)


def onnx_session(path: Path, advice: str, model: bytes | None = None):
    """A single-threaded onnxruntime session on `path` (or on `model`, a serialised part of its graph); an unreadable or
    invalid file is one UserError naming it."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = opts.inter_op_num_threads = 1  # batch-1 calls from a planner: threads cost more
    try:
        return ort.InferenceSession(model or str(path), opts, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own pybind types for unreadable or invalid graphs
        raise UserError(f"{path} is not a valid ONNX model ({str(e).splitlines()[0][:200]}); {advice}") from None


class OnnxPredictor:
    """phi(window) by onnxruntime from an exported file; a missing or corrupt file is a UserError naming it."""

    def __init__(self, path, name=None):
        """Open path with one thread; name defaults to the file's stem."""
        path = Path(path)
        self.name = name or path.stem
        if not path.exists():
            raise UserError(f"{path} not found: run `distill model={self.name}`")
        self.session = onnx_session(path, f"re-run `distill model={self.name}`")

    def phi(self, window):
        """Next xy (B, SLOTS, 2) in metres, float64."""
        x = np.ascontiguousarray(window, dtype=np.float32)
        return self.session.run(None, {"window": x})[0].astype(float)


def load_onnx(name: str, models_dir="models") -> OnnxPredictor:
    """The exported predictor models_dir/<name>.onnx."""
    return OnnxPredictor(Path(models_dir) / f"{name}.onnx", name)
