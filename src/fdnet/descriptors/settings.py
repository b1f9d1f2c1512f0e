"""A method's settings: one frozen dataclass per method, with defaults and one-line docs.

Every descriptor class declares its settings as a subclass of :class:`MethodSettings` (its
``Settings`` class attribute), as hloc declares a ``default_conf``. The fields are the method's
settings: what ``fdnet.descriptors.create(METHOD, **options)`` accepts, what ``--method-set``,
``--checkpoint``, ``--weights``, ... may set on the command line (the registry and the CLI read
the field names, :func:`fdnet.descriptors.registry.setting_names`), and what the constructor
reads. ``check()`` runs on construction and refuses a value the method cannot use with a
:class:`~fdnet.errors.ConfigError` naming the method, the setting and what is allowed, before
any weights are read.

A descriptor is built from a settings object, with keyword overrides of its fields::

    GistDescriptor(GistSettings(image_size=64))
    GistDescriptor(image_size=64)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, fields, replace
from typing import ClassVar

from fdnet.errors import ConfigError


@dataclass(frozen=True)
class MethodSettings:
    """Base of every method's settings; subclasses add fields (with defaults) and checks."""

    #: the method's name, in every message
    method: ClassVar[str] = "method"

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Refuse values the method cannot use (ConfigError naming the setting). Subclasses
        call ``super().check()`` and the helpers below."""

    @classmethod
    def declared(cls) -> tuple[str, ...]:
        """The setting names, in declaration order."""
        return tuple(f.name for f in fields(cls))

    @classmethod
    def build(cls, settings: MethodSettings | None = None, options: dict | None = None):
        """``settings`` (default: every default) with the fields in ``options`` replaced; an
        unknown name is refused, listing the method's settings."""
        options = dict(options or {})
        unknown = sorted(set(options) - set(cls.declared()))
        if unknown:
            raise ConfigError(
                f"method {cls.method!r} has no setting(s) {', '.join(unknown)}; its settings: "
                f"{', '.join(cls.declared()) or 'none'}"
            )
        if settings is None:
            return cls(**options)
        if not isinstance(settings, cls):
            raise ConfigError(f"{cls.method}: settings must be a {cls.__name__}, got {type(settings).__name__}")
        return replace(settings, **options) if options else settings

    # -- checks: each returns the value read as its type, for checks across settings ----------
    def refuse(self, name: str, allowed: str):
        raise ConfigError(f"{self.method}: {name}={getattr(self, name)!r}: {allowed}")

    def need_whole(
        self, name: str, minimum: int | None = None, maximum: int | None = None, optional: bool = False
    ) -> int | None:
        """A whole number (an int, or a float without a fraction; not a bool) in [minimum, maximum]."""
        value = getattr(self, name)
        if value is None and optional:
            return None
        allowed = _range_text("a whole number", minimum, maximum) + (" (or none)" if optional else "")
        number = whole_number(value)
        if number is None or (minimum is not None and number < minimum) or (maximum is not None and number > maximum):
            self.refuse(name, f"must be {allowed}")
        return number

    def need_number(
        self, name: str, minimum: float | None = None, maximum: float | None = None, above: float | None = None
    ) -> float:
        """A finite number in [minimum, maximum] (and > ``above``)."""
        value = getattr(self, name)
        number = None if isinstance(value, bool) or not isinstance(value, (int, float)) else float(value)
        if isinstance(value, str):
            try:
                number = float(value)
            except ValueError:
                number = None
        allowed = _range_text("a number", minimum, maximum) + (f" above {above:g}" if above is not None else "")
        if (
            number is None
            or not math.isfinite(number)
            or (minimum is not None and number < minimum)
            or (maximum is not None and number > maximum)
            or (above is not None and number <= above)
        ):
            self.refuse(name, f"must be {allowed}")
        return number

    def need_flag(self, name: str, optional: bool = False) -> bool | None:
        """true or false (or none, with ``optional``: the method chooses)."""
        value = getattr(self, name)
        if value is None and optional:
            return None
        if not isinstance(value, bool):
            self.refuse(name, "must be true or false" + (" (or none: automatic)" if optional else ""))
        return value

    def need_text(self, name: str, choices=None, optional: bool = False) -> str | None:
        """Text (one of ``choices``, compared in lower case, when given)."""
        value = getattr(self, name)
        if value is None and optional:
            return None
        if not isinstance(value, str) or (choices is not None and value.lower() not in choices):
            self.refuse(name, f"choose {' or '.join(choices)}" if choices else "must be text")
        return value

    def need_path(self, name: str) -> str | None:
        """A file or folder name (text or a path), or none."""
        value = getattr(self, name)
        if value is not None and not isinstance(value, (str, os.PathLike)):
            self.refuse(name, "must be a file or folder name")
        return None if value is None else str(value)

    def need_size(self, name: str, optional: bool = False) -> tuple[int, int] | None:
        """(height, width) in whole pixels: a pair or text ``HxW``."""
        from fdnet.data.images import check_image_size

        value = getattr(self, name)
        if value is None and optional:
            return None
        if isinstance(value, str):
            h, sep, w = value.lower().partition("x")
            pair = (whole_number(h.strip()), whole_number(w.strip())) if sep else (None, None)
        elif isinstance(value, (list, tuple)) and len(value) == 2:
            pair = tuple(whole_number(v) for v in value)
        else:
            pair = (None, None)
        if None in pair:
            self.refuse(name, "must be (height, width) in whole pixels, e.g. [32, 64] or 32x64")
        return check_image_size(pair, self.method if name == "size" else f"{self.method}: {name}")

    def need_device(self, name: str = "device") -> None:
        """``auto``, ``cpu``, ``cuda`` or ``cuda:N`` (or a torch.device; none = auto)."""
        from fdnet.backbones import check_device_spec

        value = getattr(self, name)
        if isinstance(value, str):
            check_device_spec(value, where=f"{self.method}: {name}")
        elif value is not None and type(value).__name__ != "device":
            self.refuse(name, "choose auto, cpu, cuda or cuda:N")

    def need_backbone(self, name: str = "backbone", optional: bool = False) -> None:
        """One of the shipped backbones (efficientnet-lite0, -lite1, -lite2)."""
        from fdnet.backbones import check_backbone

        value = getattr(self, name)
        if value is None and optional:
            return
        if not isinstance(value, str):
            self.refuse(name, "must be a backbone's name, e.g. efficientnet-lite0")
        check_backbone(value, where=f"{self.method}: {name}")

    def need_block(self, backbone: str | None, name: str = "block", optional: bool = False) -> int | None:
        """A block of ``backbone`` (default EfficientNet-Lite0)."""
        from fdnet.backbones import check_block

        block = self.need_whole(name, minimum=0, optional=optional)
        if block is None:
            return None
        try:
            return check_block(block, backbone)
        except ConfigError as exc:
            raise ConfigError(f"{self.method}: {name}: {exc}") from exc

    def need_numbers(self, name: str, length: int | None = None, minimum: float | None = None) -> tuple[float, ...]:
        """A list of numbers (``length`` of them, each >= ``minimum``)."""
        value = getattr(self, name)
        items = list(value) if isinstance(value, (list, tuple)) else None
        ok = (
            items is not None
            and (length is None or len(items) == length)
            and len(items) > 0
            and all(
                not isinstance(v, bool)
                and isinstance(v, (int, float))
                and math.isfinite(v)
                and (minimum is None or v >= minimum)
                for v in items
            )
        )
        if not ok:
            count = f"{length} numbers" if length else "a list of numbers"
            self.refuse(name, f"must be {count}" + (f", each >= {minimum:g}" if minimum is not None else ""))
        return tuple(float(v) for v in items)


def whole_number(value) -> int | None:
    """``value`` as an int when it is a whole number (an int, a float or text with no fraction;
    not a bool), else None: :func:`fdnet.data.images.whole_number`'s rule, with numeric text
    read as YAML would and a refusal as None."""
    from fdnet.data.images import whole_number as whole

    if isinstance(value, str):
        try:
            value = float(value) if any(c in value for c in ".eE") else int(value)
        except ValueError:
            return None
    try:
        number = whole(value)
    except (TypeError, ValueError, OverflowError):
        return None
    return number if number == value else None


def _range_text(what: str, minimum, maximum) -> str:
    if minimum is not None and maximum is not None:
        return f"{what} from {minimum} to {maximum}"
    if minimum is not None:
        return f"{what} >= {minimum}"
    if maximum is not None:
        return f"{what} <= {maximum}"
    return what
