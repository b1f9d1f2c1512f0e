"""Errors a user can act on.

Anything raised as :class:`FdnetError` is printed by the CLI as one clear line (no traceback):
the message must name the file (and line, where there is one) and what is wrong with it.
"""

import functools
from typing import Callable


class FdnetError(Exception):
    """Base class: a problem with the user's input, data or configuration."""


class DataError(FdnetError):
    """An image, folder or ground-truth file that cannot be used as it is."""


class ConfigError(FdnetError):
    """A setting, preset, checkpoint or command-line combination that cannot work."""


class OutputError(ConfigError, OSError):
    """An output that cannot be written (a full disk, a read-only folder). Also an OSError, so
    code that tolerates a failed write (a cache) still does."""


class NotAvailableError(FdnetError):
    """A method that cannot run here without something the user must supply (e.g. weights)."""


def invalid_settings_are_config_errors(init: Callable) -> Callable:
    """Decorator for the baseline descriptors' constructors: a setting of the wrong type or value
    (e.g. ``--method-set gist:image_size=big``) becomes a one-line :class:`ConfigError` naming the
    method instead of a traceback. ``functools.wraps`` keeps the signature visible to the registry."""

    @functools.wraps(init)
    def wrapper(self, *args, **kwargs):
        try:
            return init(self, *args, **kwargs)
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{self.name}: invalid setting ({exc})") from None

    return wrapper
