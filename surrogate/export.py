"""ONNX export of the surrogate (optionally fused with the source predictor's forward pass), source in the metadata."""
import onnx
import torch

from core.jobs import atomic_file


def export(module, path, T_obs, M, source, opset=17):
    """Write `module` (window (B, T_obs, SLOTS, 2) -> J, or (J, next) when fused) to `path` with metadata `source`."""
    module = module.float().eval()
    window = torch.zeros(1, T_obs, M, 2)
    with torch.no_grad():
        outputs = module(window)
    names = ["J", "next"] if isinstance(outputs, tuple) else ["J"]

    def write(tmp):
        # dynamo=False: the TorchScript exporter needs no onnxscript, and these MLPs trace exactly
        torch.onnx.export(module, (window,), str(tmp), input_names=["window"], output_names=names, opset_version=opset,
                          dynamic_axes={n: {0: "B"} for n in ["window", *names]}, dynamo=False)
        model = onnx.load(str(tmp))
        onnx.helper.set_model_props(model, {"source": source, "T_obs": str(T_obs), "M": str(M)})
        onnx.save(model, str(tmp))

    atomic_file(path, write)
