"""`fdnet export`: a trained FDNet's content encoder as an ONNX model."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "export",
        help="export a trained FDNet run's descriptor to ONNX",
        description="Write an ONNX graph: images (N,3,H,W) float32 RGB in [0,1] -> L2-normalised "
        "content vectors (N,L), preprocessing included; checked against PyTorch "
        "with onnxruntime.",
    )
    p.add_argument("--checkpoint", required=True, help="FDNet run directory (from fdnet train), or its best/")
    p.add_argument("--out", required=True, help="ONNX file to write")
    p.add_argument("--opset", type=int, default=17)
    p.add_argument("--no-check", action="store_true", help="skip the onnxruntime comparison")
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.errors import FdnetError
    from fdnet.export import export_onnx

    result = export_onnx(args.checkpoint, args.out, opset=args.opset, check=not args.no_check)
    h, w = result["input_size"]
    print(f"wrote {result['path']}: images (N, 3, {h}, {w}) float32 in [0, 1] -> content (N, {result['dim']})")
    if result["max_abs_diff"] is not None:
        print(f"onnxruntime vs PyTorch on 4 random images: max abs difference {result['max_abs_diff']:.2e}")
        if result["max_abs_diff"] > 1e-3:
            raise FdnetError(f"{result['path']}: ONNX output differs from PyTorch by {result['max_abs_diff']:.2e}")
    return 0
