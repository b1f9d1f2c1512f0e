"""`fdnet train-baseline METHOD`: an alias of `fdnet train METHOD` for the trained baselines
(kept so documented commands and scripts keep working; it says so on standard error)."""

from __future__ import annotations


def register(sub) -> None:
    from fdnet.cli.train import DEFAULT_METHOD, add_arguments
    from fdnet.descriptors.registry import trained_methods

    methods = [m for m in trained_methods() if m != DEFAULT_METHOD]
    p = sub.add_parser("train-baseline", help=f"alias of `fdnet train METHOD` for {', '.join(methods)}",
                       description="An alias of `fdnet train METHOD` (the same flags and behaviour); "
                                   "use `fdnet train METHOD`.")
    add_arguments(p, methods, default=None)
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.cli import train

    train.note_alias(args)
    return train.run(args)
