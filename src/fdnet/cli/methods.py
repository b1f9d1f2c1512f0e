"""`fdnet methods`: list the methods usable with --method (from the method registry)."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser(
        "methods",
        help="list the place-recognition methods (--method names) and what each supports",
        description="One line per method: its name, what it supports (trained with `fdnet train "
        "METHOD` and its presets, torch device, --fit, ONNX export) and a summary.",
    )
    p.add_argument("--markdown", action="store_true", help="print the table of docs/methods.md instead")
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.descriptors.registry import all_specs, methods_markdown

    if args.markdown:
        print(methods_markdown(), end="")
        return 0
    specs = all_specs()
    width = max(len(s.name) for s in specs)
    for s in specs:
        tags = [f"train: {'|'.join(s.presets)}"] if s.trained else []
        tags += ["device"] * s.torch + ["--fit"] * s.fit + ["export"] * s.export
        print(f"{s.name:{width}s} {s.summary}" + (f" [{'; '.join(tags)}]" if tags else ""))
    return 0
