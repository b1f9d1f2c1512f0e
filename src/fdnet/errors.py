"""Errors a user can act on.

Anything raised as :class:`FdnetError` is printed by the CLI as one clear line (no traceback):
the message must name the file (and line, where there is one) and what is wrong with it.
"""


class FdnetError(Exception):
    """Base class: a problem with the user's input, data or configuration."""


class DataError(FdnetError):
    """An image, folder or ground-truth file that cannot be used as it is."""


class ConfigError(FdnetError):
    """A setting, preset, checkpoint or command-line combination that cannot work."""


class NotAvailableError(FdnetError):
    """A method that cannot run here without something the user must supply (e.g. weights)."""
