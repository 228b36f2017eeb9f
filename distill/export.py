"""ONNX export of a predictor network and an onnxruntime predictor that reads it back (numpy in, numpy out, metres)."""
from pathlib import Path

import numpy as np

from core.jobs import UserError, atomic_file


def export_onnx(module, path: Path, t_obs: int, m: int):
    """Write the torch `module` (window (B, T_obs, SLOTS, 2) -> next (B, SLOTS, 2)) traced at windows of t_obs steps and
    m = SLOTS cars to `path` atomically, batch size dynamic; a hypothesis network (one with a belief) as (window,
    hypothesis (B, SLOTS)) -> (next, belief (B, SLOTS))."""
    import torch  # here, not at the top: the planner reads ONNX files through this module without torch

    class Answers(torch.nn.Module):
        """A hypothesis network's next positions under the hypotheses and its belief, as one graph."""

        def __init__(self, net):
            super().__init__()
            self.net = net

        def forward(self, window, hypothesis):
            return self.net(window, hypothesis), self.net.belief(window)

    hyp = hasattr(module, "belief")
    example = (torch.zeros(2, t_obs, m, 2),) + ((torch.zeros(2, m),) if hyp else ())
    inputs, outputs = (["window", "hypothesis"], ["next", "belief"]) if hyp else (["window"], ["next"])

    def write(tmp):
        """Export to the temporary path."""
        # the legacy TorchScript exporter: the dynamo one needs onnxscript, which is not a dependency
        torch.onnx.export((Answers(module) if hyp else module).eval(), example, str(tmp), input_names=inputs,
                          output_names=outputs, dynamic_axes={k: {0: "batch"} for k in inputs + outputs}, opset_version=17,
                          dynamo=False)

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

    def answers(self, window, hyp):
        """A hypothesis model's next xy (B, SLOTS, 2) (m) under hypotheses hyp (B, SLOTS) and its belief (B, SLOTS),
        float64."""
        feed = {"window": np.ascontiguousarray(window, dtype=np.float32), "hypothesis": np.ascontiguousarray(hyp, dtype=np.float32)}
        return tuple(a.astype(float) for a in self.session.run(None, feed))


def load_onnx(name: str, models_dir="models") -> OnnxPredictor:
    """The exported predictor models_dir/<name>.onnx."""
    return OnnxPredictor(Path(models_dir) / f"{name}.onnx", name)
