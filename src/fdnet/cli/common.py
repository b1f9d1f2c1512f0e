"""Arguments and helpers shared by several sub-commands (method selection, threads)."""

from __future__ import annotations

import argparse
import os


def add_method_arguments(parser: argparse.ArgumentParser, multiple: bool = False, required: bool = True) -> None:
    """--method plus the options any method may take (passed to ``fdnet.descriptors.create``).
    ``required=False`` for commands where --method is one of several input modes."""
    parser.add_argument("--method", required=required,
                        help="descriptor method" + (" (comma-separated for several)" if multiple else "")
                        + "; `fdnet methods` lists them")
    parser.add_argument("--checkpoint", help="run directory of a trained method (fdnet, netvlad, calc)")
    parser.add_argument("--weights", help="weights file a method accepts (conv3 AlexNet, hybridnet)")
    parser.add_argument("--vocabulary", help="DBoW vocabulary file (from `fdnet vocabulary build`)")
    parser.add_argument("--method-set", action="append", default=[], metavar="KEY=VALUE",
                        help="a method setting, e.g. --method-set dim=1024 (repeatable)")


def method_options(args: argparse.Namespace) -> dict:
    """Keyword options for ``create`` from parsed arguments (YAML-typed values)."""
    import yaml

    from fdnet.config import parse_overrides

    options = {"checkpoint": args.checkpoint, "weights": args.weights, "vocabulary": args.vocabulary}
    for key, value in parse_overrides(getattr(args, "method_set", [])).items():
        options[key] = yaml.safe_load(value)
    return options


def create_descriptor(name: str, args: argparse.Namespace):
    from fdnet.descriptors import create

    return create(name, **method_options(args))


def set_threads(threads: int | None) -> None:
    """Use all cores by default; an explicit count makes runs comparable on shared machines."""
    import torch

    torch.set_num_threads(threads or os.cpu_count() or 1)
