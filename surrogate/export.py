"""ONNX export of the surrogate (optionally fused with the source predictor's forward pass), the source predictor and the
shapes in the metadata."""
import onnx
import torch

from core.jobs import atomic_file


def write(module, path, inputs: dict, outputs: list, metadata: dict, opset=17):
    """Write `module` traced on example `inputs` {name: tensor} with `outputs` named, batch axis 0 dynamic, to `path`."""
    module = module.float().eval()

    def save(tmp):
        # dynamo=False: the TorchScript exporter needs no onnxscript, and these networks trace exactly
        torch.onnx.export(module, tuple(inputs.values()), str(tmp), input_names=list(inputs), output_names=outputs,
                          opset_version=opset, dynamic_axes={n: {0: "B"} for n in [*inputs, *outputs]}, dynamo=False)
        model = onnx.load(str(tmp))
        onnx.helper.set_model_props(model, {k: str(v) for k, v in metadata.items()})
        onnx.save(model, str(tmp))

    atomic_file(path, save)


def export(module, path, T_obs, M, source, source_sha256="", opset=17):
    """Write `module` (window (B, T_obs, SLOTS, 2) -> J, or (J, next) when fused) to `path` with metadata `source` and
    `source_sha256`, the sha256 of the source's checkpoint it learned ("": none read)."""
    window = torch.zeros(1, T_obs, M, 2)
    with torch.no_grad():
        outputs = module.float().eval()(window)
    names = ["J", "next"] if isinstance(outputs, tuple) else ["J"]
    write(module, path, {"window": window}, names, {"source": source, "source_sha256": source_sha256, "T_obs": T_obs, "M": M},
          opset)
