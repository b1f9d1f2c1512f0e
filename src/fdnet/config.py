"""Dataclass configs serialised to YAML, with ``key.sub=value`` overrides.

One config object describes a run; it is written next to the run's checkpoint so that a run
directory is self-describing (as OpenVPRLab does).
"""

from __future__ import annotations

import dataclasses
import reprlib
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from fdnet.errors import ConfigError

T = TypeVar("T")


def to_dict(config: Any) -> dict:
    """Dataclass (nested) -> plain dict of YAML-safe values (tuples become lists)."""

    def plain(value):
        if dataclasses.is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, Path):
            return str(value)
        return value

    return plain(config)


#: what an error message shows of a wrong value at most: a value built from YAML aliases can be
#: gigabytes long once expanded, and the message must stay one line
SHOWN_CHARACTERS = 200


def _shown(value: Any) -> str:
    shortened = reprlib.Repr()  # its keyword arguments need Python 3.12
    shortened.maxstring = shortened.maxother = SHOWN_CHARACTERS
    shortened.maxlist = shortened.maxtuple = shortened.maxdict = 10
    shortened.maxlevel = 3
    text = shortened.repr(value)
    return text if len(text) <= SHOWN_CHARACTERS else text[:SHOWN_CHARACTERS] + "..."


def _coerce(tp: Any, value: Any, where: str) -> Any:
    """Convert a YAML/CLI value to the field's declared type, with a clear error."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: cannot use {_shown(value)}")
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {_shown(value)}")
        return from_dict(tp, value, where=where)
    if origin in (tuple, list):
        if isinstance(value, str):
            value = [v for v in value.replace(",", " ").split() if v]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {_shown(value)}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {_shown(list(value))}")
            return tuple(_coerce(a, v, where) for a, v in zip(args, value))
        inner = args[0] if args else Any
        items = [_coerce(inner, v, where) for v in value]
        return tuple(items) if origin is tuple else items
    if tp is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "yes", "1", "on"):
            return True
        if isinstance(value, str) and value.lower() in ("false", "no", "0", "off"):
            return False
        raise ConfigError(f"{where}: expected true/false, got {_shown(value)}")
    if tp in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float, str)):
            raise ConfigError(f"{where}: expected a number, got {_shown(value)}")
        try:
            number = float(value) if tp is float else int(str(value), 0) if isinstance(value, str) else value
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{where}: expected {tp.__name__}, got {_shown(value)}") from exc
        if tp is int and isinstance(number, float):
            if not number.is_integer():
                raise ConfigError(f"{where}: expected an integer, got {_shown(value)}")
            number = int(number)
        return tp(number)
    if tp is str:
        if isinstance(value, (list, tuple, dict)):
            raise ConfigError(f"{where}: expected text, got {_shown(value)}")
        return str(value)
    return value


def from_dict(cls: type[T], data: dict, where: str = "config") -> T:
    """Build dataclass ``cls`` from a dict; unknown keys are an error naming the valid ones."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown setting(s) {', '.join(unknown)}; valid: {', '.join(fields)}")
    kwargs = {name: _coerce(hints[name], value, f"{where}.{name}") for name, value in data.items()}
    return cls(**kwargs)


def replace_dotted(config: T, overrides: dict[str, Any]) -> T:
    """Return a copy of ``config`` with ``{"a.b": value}`` overrides applied (values coerced)."""
    data = to_dict(config)
    for key, value in overrides.items():
        node = data
        parts = key.split(".")
        for part in parts[:-1]:
            if not isinstance(node.get(part), dict):
                raise ConfigError(f"override {key}: {part!r} is not a group of settings")
            node = node[part]
        if parts[-1] not in node:
            raise ConfigError(f"override {key}: unknown setting {parts[-1]!r}; valid: {', '.join(node)}")
        current = node[parts[-1]]
        # Text settings keep the text as given: YAML would read "0:37" as the base-60 number 2265.
        if isinstance(value, str) and not isinstance(current, str):
            value = parse_value(value, f"override {key}")
        node[parts[-1]] = value
    return from_dict(type(config), data)


def parse_value(text: str, where: str) -> Any:
    """A setting's value given as text (``--set``, ``--method-set``), read as YAML without
    aliases; a ConfigError naming ``where`` when it is not YAML."""
    import re

    if re.fullmatch(r"\s*\d+\s*[xX]\s*\d+\s*", str(text)):
        return str(text).strip()  # a size such as 0x0 or 32x64, not YAML's hexadecimal integer 0x0
    try:
        return yaml.load(text, Loader=_NoAliasLoader)  # noqa: S506 (safe, no aliases)
    except yaml.YAMLError as exc:
        raise ConfigError(f"{where}: {_shown(text)} is not a valid YAML value ({_yaml_problem(exc)})") from exc
    except RecursionError as exc:
        raise ConfigError(f"{where}: {_shown(text)} is nested deeper than {MAX_NESTING} levels") from exc


def parse_overrides(items: list[str] | None) -> dict[str, str]:
    """``["a.b=1", "c=x"]`` -> ``{"a.b": "1", "c": "x"}``."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE")
        key, value = item.split("=", 1)
        out[key.strip()] = value.strip()
    return out


#: the largest settings file read (a run's config.yaml is a few KiB): a larger one is refused
#: before it is parsed
MAX_YAML_BYTES = 1 << 20


class _NoAliasLoader(yaml.SafeLoader):
    """Safe YAML without aliases (``*name``): settings never need them, and a few hundred bytes
    of nested aliases expand into gigabytes of values (a "billion laughs")."""

    def compose_node(self, parent, index):
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None,
                None,
                f"found an alias (*{event.anchor}); aliases are not "
                "allowed in fdnet settings files: write the value out",
                event.start_mark,
            )
        return super().compose_node(parent, index)


def read_yaml_file(path: str | Path, what: str = "config file", error: type = ConfigError) -> Any:
    """The value of a YAML settings or run file: no aliases, at most :data:`MAX_YAML_BYTES`,
    errors (``error``) naming the file. FileNotFoundError is left to the caller."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_YAML_BYTES:
        raise error(f"{path}: {size} bytes, too large for a {what} (at most {MAX_YAML_BYTES // 1024} KiB)")
    try:
        value = yaml.load(path.read_text(encoding="utf-8"), Loader=_NoAliasLoader)  # noqa: S506 (safe, no aliases)
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a text {what} ({exc.reason} at byte {exc.start})") from exc
    except yaml.YAMLError as exc:
        raise error(f"{path}: not valid YAML ({_yaml_problem(exc)})") from exc
    except RecursionError as exc:
        raise error(f"{path}: nested deeper than any {what} is (at most {MAX_NESTING} levels)") from exc
    check_nesting(value, f"{path}: a {what}", error)
    return value


#: how deep settings files and stored JSON may nest: every fdnet file is a few levels deep; a file
#: nested thousands deep is hostile and would exhaust Python's recursion while being read
MAX_NESTING = 64


def check_nesting(value: Any, where: str, error: type = ConfigError) -> None:
    """Refuse (``error``) a value of mappings and lists nested deeper than :data:`MAX_NESTING`
    (walked without recursion, so the check itself cannot overflow)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if depth > MAX_NESTING:
            raise error(f"{where} nested deeper than {MAX_NESTING} levels")
        if isinstance(item, dict):
            stack.extend((child, depth + 1) for child in item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend((child, depth + 1) for child in item)


def load_json_text(text: str, where: str, error: type = ConfigError) -> Any:
    """JSON text as a value, with a too-deep nesting refused like a settings file's."""
    import json

    try:
        value = json.loads(text)
    except RecursionError as exc:
        raise error(f"{where}: nested deeper than {MAX_NESTING} levels") from exc
    check_nesting(value, where, error)
    return value


def _yaml_problem(exc: yaml.YAMLError) -> str:
    """One line: where and what (PyYAML's own text spans several lines with a snippet)."""
    mark = getattr(exc, "problem_mark", None)
    problem = " ".join(str(part) for part in (getattr(exc, "context", None), getattr(exc, "problem", None)) if part)
    text = (
        f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
        if mark is not None and problem
        else " ".join(str(exc).split())
    )
    return text if len(text) <= 2 * SHOWN_CHARACTERS else text[: 2 * SHOWN_CHARACTERS] + "..."


def read_yaml_mapping(path: str | Path) -> dict:
    """The top-level mapping of a YAML settings file, with errors naming the file."""
    path = Path(path)
    try:
        data = read_yaml_file(path) or {}
    except FileNotFoundError as exc:
        raise ConfigError(f"{path}: config file not found") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of settings at the top level")
    return data


def load_yaml(cls: type[T], path: str | Path) -> T:
    return from_dict(cls, read_yaml_mapping(path), where=str(path))


def flatten_dotted(data: dict, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (the names ``--set`` takes)."""
    out = {}
    for key, value in data.items():
        if isinstance(value, dict):
            out.update(flatten_dotted(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def apply_yaml(config: T, path: str | Path) -> T:
    """Apply a YAML file holding any subset of the settings tree on top of ``config``."""
    data = read_yaml_mapping(path)
    try:
        return replace_dotted(config, flatten_dotted(data))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from exc
