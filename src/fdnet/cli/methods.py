"""`fdnet methods`: list the descriptor methods usable with --method."""

from __future__ import annotations


def register(sub) -> None:
    p = sub.add_parser("methods", help="list the place-recognition methods (--method names)")
    p.set_defaults(func=run)


def run(args) -> int:
    from fdnet.descriptors.registry import available_methods

    methods = available_methods()
    width = max(map(len, methods))
    for name, summary in methods.items():
        print(f"{name:{width}s} {summary}")
    return 0
