"""Old flag spellings kept working: each is a hidden alias of the flag that replaced it (same
destination, same type), and using it logs one line saying the new spelling
(``fdnet COMMAND: warning: --frames is the old spelling of --num-frames; ...``). docs/flags.md
lists every flag with its old spellings."""

from __future__ import annotations

import argparse

#: namespace attribute where the parser records the old spellings used, for :func:`note_old_spellings`
USED = "old_spellings_used"
#: parser default listing (dest, new spelling) of required flags that have an old spelling: argparse
#: would refuse the old spelling of a required flag, so :func:`note_old_spellings` checks them instead
REQUIRED = "renamed_required_flags"


def add_old_spelling(parser, old: str, new: str) -> None:
    """Accept ``old`` wherever ``parser`` (or an argument group of it) has ``new``, as the same
    setting; the command logs a deprecation note when ``old`` is used."""
    target = parser._option_string_actions[new]
    base = type(target)
    if target.required:
        target.required = False
        parser._defaults[REQUIRED] = [*parser._defaults.get(REQUIRED, []), (target.dest, new)]

    class OldSpelling(base):
        def __call__(self, parser_, namespace, values, option_string=None):
            used = getattr(namespace, USED, None) or []
            setattr(namespace, USED, [*used, (old, new)])
            super().__call__(parser_, namespace, values, option_string)

    kwargs = dict(dest=target.dest, default=argparse.SUPPRESS, help=argparse.SUPPRESS, action=OldSpelling)
    if target.nargs != 0:  # a switch (store_true) takes no value settings
        kwargs.update(nargs=target.nargs, type=target.type, choices=target.choices, metavar=target.metavar)
        if target.const is not None:
            kwargs["const"] = target.const
    parser.add_argument(old, **kwargs)


def add_old_spellings(parser, renamed: dict[str, str]) -> None:
    """:func:`add_old_spelling` for each ``{old: new}``."""
    for old, new in renamed.items():
        add_old_spelling(parser, old, new)


def note_old_spellings(args: argparse.Namespace) -> None:
    """Log one warning per old spelling the command line used (inside the command's logging), and
    refuse a required flag given in neither spelling."""
    import logging

    from fdnet.errors import ConfigError

    for dest, new in getattr(args, REQUIRED, None) or []:
        if getattr(args, dest, None) is None:
            raise ConfigError(f"the following arguments are required: {new}")

    for old, new in dict.fromkeys(getattr(args, USED, None) or []):
        logging.getLogger("fdnet.cli").warning(f"{old} is the old spelling of {new} (same meaning); "
                                               f"it still works, but write {new}")


def add_shared_old_spellings(subparsers) -> None:
    """Old spellings every command shares: ``--methods`` for ``--method`` (one comma-separated
    list everywhere). Called by ``fdnet.cli.build_parser`` on every (sub-)command."""
    for parser in set(subparsers.choices.values()):
        nested = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for action in nested:
            add_shared_old_spellings(action)
        options = parser._option_string_actions
        if not nested and "--method" in options and "--methods" not in options:
            add_old_spelling(parser, "--methods", "--method")
