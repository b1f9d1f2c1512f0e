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
    per_method = " (with several methods: METHOD=PATH, repeatable; a bare PATH goes to every method that takes one)"
    parser.add_argument("--checkpoint", action="append", default=[],
                        help="run directory of a trained method (fdnet, netvlad, calc)" + per_method)
    parser.add_argument("--weights", action="append", default=[],
                        help="weights file a method accepts (conv3 AlexNet, hybridnet)" + per_method)
    parser.add_argument("--vocabulary", action="append", default=[],
                        help="DBoW vocabulary file (from `fdnet vocabulary build`)" + per_method)
    parser.add_argument("--method-set", action="append", default=[], metavar="[METHOD:]KEY=VALUE",
                        help="a method setting, e.g. --method-set dim=1024 or --method-set conv3:dim=1024 "
                             "(repeatable)")


FILE_OPTIONS = ("checkpoint", "weights", "vocabulary")


def _for_method(values, method: str, known_methods) -> str | None:
    """Pick the value meant for ``method`` from repeated ``[METHOD=]PATH`` arguments."""
    if values is None or isinstance(values, str):
        values = [values] if values else []
    chosen = None
    for value in values:
        prefix, sep, rest = value.partition("=")
        if sep and prefix in known_methods:
            if prefix == method:
                chosen = rest
        elif chosen is None:
            chosen = value
    return chosen


def method_options(args: argparse.Namespace, method: str | None = None) -> dict:
    """Keyword options for ``create(method, ...)`` from parsed arguments (YAML-typed values).

    File options given as ``METHOD=PATH`` go to that method only; bare paths go to every method
    whose constructor takes that option (so ``--method fdnet,sad --checkpoint RUN`` works).
    """
    import inspect

    import yaml

    from fdnet.config import parse_overrides
    from fdnet.descriptors.registry import available_methods, descriptor_class

    from fdnet.errors import ConfigError

    known = available_methods()

    def takes(name: str) -> set:
        return set(inspect.signature(descriptor_class(name).__init__).parameters)

    accepted = takes(method) if method is not None else None
    requested = [m.strip() for m in (getattr(args, "method", None) or "").split(",") if m.strip() in known]
    for key in FILE_OPTIONS:
        for value in getattr(args, key, None) or []:
            prefix, sep, _ = str(value).partition("=")
            if not (sep and prefix in known) and requested and not any(key in takes(m) for m in requested):
                raise ConfigError(f"--{key} {value}: none of the methods {', '.join(requested)} takes a {key}")
    options = {}
    for key in FILE_OPTIONS:
        value = _for_method(getattr(args, key, None), method, known)
        explicit = any(str(v).startswith(f"{method}=") for v in (getattr(args, key, None) or []))
        if value is not None and (accepted is None or key in accepted or explicit):
            options[key] = value
    for key, value in parse_overrides(getattr(args, "method_set", [])).items():
        target, sep, setting = key.partition(":")
        if sep:
            if target == method:
                options[setting] = yaml.safe_load(value)
        else:
            options[key] = yaml.safe_load(value)
    return options


def create_descriptor(name: str, args: argparse.Namespace):
    from fdnet.descriptors import create

    return create(name, **method_options(args, name))


def set_threads(threads: int | None) -> None:
    """Use all cores by default; an explicit count makes runs comparable on shared machines."""
    import torch

    torch.set_num_threads(threads or os.cpu_count() or 1)
