"""Export a trained FDNet's content encoder to ONNX, for deployment without PyTorch.

The exported graph takes ``images``: float32 (N, 3, H, W) RGB in [0, 1] at the run's input size
(NCHW, as ONNX runtimes expect) and returns ``content``: (N, L) L2-normalised content vectors —
exactly what ``fdnet.load(run).describe`` gives, preprocessing included, so a deployment needs no
fdnet code. The model's metadata says so (``fdnet.input_size`` etc.), so ``--method onnx
--weights FILE`` reads it back with no settings. The export is checked against PyTorch with
onnxruntime on random images.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from fdnet.errors import NotAvailableError


def _content_module(descriptor):
    import torch

    class ContentDescriptor(torch.nn.Module):
        def __init__(self, model):
            super().__init__()
            self.model = model

        def forward(self, images):
            return torch.nn.functional.normalize(self.model.content(images), dim=1)

    return ContentDescriptor(descriptor.model).eval()


def export_onnx(
    run_dir: str | os.PathLike, out: str | os.PathLike, opset: int = 17, check: bool = True, seed: int = 0
) -> dict:
    """Write ``out`` (atomically) and return ``{"path", "input_size", "dim", "max_abs_diff"}``;
    ``max_abs_diff`` compares onnxruntime with PyTorch on 4 random images (None without check)."""
    import torch

    from fdnet.io import atomic_path, ensure_writable
    from fdnet.methods.fdnet.descriptor import FDNetDescriptor

    ensure_writable(out, what="ONNX file")  # before the minutes of tracing and checking

    try:
        import onnx
    except ImportError as exc:
        raise NotAvailableError(
            "ONNX export needs the optional extra: pip install 'fdnet[onnx]' " "(onnx and onnxruntime)"
        ) from exc
    descriptor = FDNetDescriptor.from_run(run_dir)
    module = _content_module(descriptor)
    height, width = descriptor.input_size
    example = torch.rand(2, 3, height, width, generator=torch.Generator().manual_seed(seed))
    out = Path(out)
    with atomic_path(out) as tmp, warnings.catch_warnings():
        # The TorchScript-based exporter: no extra dependency (onnxscript) and stable for plain
        # conv/linear graphs like this one; its deprecation notice is not the user's concern.
        warnings.simplefilter("ignore", DeprecationWarning)
        # The backbone's "same" padding is computed from the input size in Python; the graph is
        # traced at the run's fixed input size, so the tracer's warnings about it do not apply.
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        torch.onnx.export(
            module,
            (example,),
            str(tmp),
            input_names=["images"],
            output_names=["content"],
            dynamic_axes={"images": {0: "batch"}, "content": {0: "batch"}},
            opset_version=opset,
            dynamo=False,
        )
        # What `--method onnx` reads so the file needs no settings: the input size, RGB in [0, 1].
        from fdnet.descriptors.onnx_model import model_metadata

        graph = onnx.load(str(tmp))
        onnx.helper.set_model_props(
            graph,
            {
                **model_metadata((height, width)),
                "fdnet.method": "fdnet",
                "fdnet.run": str(Path(run_dir).resolve().name),
            },
        )
        onnx.save(graph, str(tmp))
    result = {"path": str(out), "input_size": [height, width], "dim": descriptor.dim, "max_abs_diff": None}
    if check:
        import onnxruntime

        images = np.random.default_rng(seed).random((4, 3, height, width), dtype=np.float32)
        session = onnxruntime.InferenceSession(str(out), providers=["CPUExecutionProvider"])
        onnx_vectors = session.run(["content"], {"images": images})[0]
        with torch.inference_mode():
            torch_vectors = module(torch.from_numpy(images)).numpy()
        result["max_abs_diff"] = float(np.abs(onnx_vectors - torch_vectors).max())
    return result
