"""Typed configs: frozen dataclasses <-> YAML, with dotted overrides and errors that name the key.

Every component declares a frozen dataclass with a docstring line under each field::

    @dataclass(frozen=True)
    class OptimConfig:
        lr: float = 1e-4
        \"\"\"Peak learning rate of AdamW.\"\"\"
        betas: tuple[float, float] = (0.9, 0.999)

Configs hold only plain values (numbers, strings, booleans, tuples, nested configs), so they save and load as
plain YAML. Loading checks every key and type: a typo is an error that lists the valid keys.

    cfg = load_config(TrainConfig, "configs/flashocc_m0.yaml", overrides=["optim.lr=2e-4"])
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import difflib
import functools
import inspect
import math
import textwrap
import types
import typing
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

__all__ = [
    "ConfigError",
    "MISSING",
    "leaf_differences",
    "to_dict",
    "from_dict",
    "load_config",
    "save_config",
    "dump_yaml",
    "apply_overrides",
    "override_dict",
    "field_docs",
    "check_ranges",
    "check_magnitudes",
]

C = TypeVar("C")


class ConfigError(ValueError):
    """A config value or key is invalid; the message names the dotted key and, if given, the file."""


# ----------------------------------------------------------------------------------------------- dataclass -> dict
def to_dict(cfg: Any) -> Any:
    """Plain nested dict/list/scalar form of a config (tuples become lists), ready for YAML or JSON."""
    if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type):
        return {f.name: to_dict(getattr(cfg, f.name)) for f in dataclasses.fields(cfg)}
    if isinstance(cfg, (list, tuple)):
        return [to_dict(v) for v in cfg]
    if isinstance(cfg, Mapping):
        return {str(k): to_dict(v) for k, v in cfg.items()}
    return cfg


# ----------------------------------------------------------------------------------------------- dict -> dataclass
@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def _convert(value: Any, tp: Any, key: str) -> Any:
    """Check ``value`` against the annotation ``tp`` and convert it (lists -> tuples, int -> float, dict -> config)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        for option in options:
            try:
                return _convert(value, option, key)
            except ConfigError:
                if len(options) == 1:  # an optional value (X | None): X's own error names the inner key
                    raise
                continue
        raise ConfigError(f"{key}: {value!r} matches none of {_type_name(tp)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{key}: {value!r} is not one of {', '.join(repr(a) for a in args)}")
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, key)
    if origin in (tuple, list, Sequence):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list for {_type_name(tp)}, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(value) != len(args):
                raise ConfigError(f"{key}: expected {len(args)} values for {_type_name(tp)}, got {len(value)}")
            return tuple(_convert(v, a, f"{key}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
        item = args[0] if args else Any
        return tuple(_convert(v, item, f"{key}[{i}]") for i, v in enumerate(value))
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{key}: expected a mapping, got {value!r}")
        value_type = args[1] if args else Any
        return {str(k): _convert(v, value_type, f"{key}.{k}") for k, v in value.items()}
    return _convert_scalar(value, tp, key)


def _convert_scalar(value: Any, tp: Any, key: str) -> Any:
    # bool is a subclass of int in Python: keep `true` out of int/float fields and 1 out of bool fields.
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        number = None
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            number = float(value)
        elif isinstance(value, str):
            # PyYAML follows YAML 1.1, which reads "1e-4" (no dot) as a string; users mean a number.
            with contextlib.suppress(ValueError):
                number = float(value)
        if number is not None:
            # No setting of occkit means "not a number" or "infinite": a NaN rate or size would run on silently.
            if not math.isfinite(number):
                raise ConfigError(f"{key}: expected a finite number, got {value!r}")
            return number
    elif tp is str:
        if isinstance(value, str):
            return value
    elif tp is type(None):
        if value is None:
            return None
    else:
        raise ConfigError(f"{key}: unsupported annotation {_type_name(tp)} (configs hold plain values only)")
    raise ConfigError(f"{key}: expected {_type_name(tp)}, got {value!r} ({type(value).__name__})")


def _unknown_key_message(key: str, where: str, valid: Sequence[str]) -> str:
    close = difflib.get_close_matches(key, valid, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return f"{where}: unknown key {key!r}{hint}; valid keys: {', '.join(valid)}"


def from_dict(cls: type[C], data: Mapping[str, Any], where: str = "config") -> C:
    """Build config ``cls`` from a mapping, checking every key and type.

    Missing keys take the field defaults; unknown keys and wrong types raise :class:`ConfigError` naming the
    dotted key (``where`` is the prefix used in messages, e.g. the file name). Keys a config class lists in its
    ``RETIRED_KEYS`` (key -> what replaced it) are skipped, so older files and checkpoints still load; a true value
    warns.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping for {cls.__name__}, got {data!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = _hints(cls)
    retired = getattr(cls, "RETIRED_KEYS", {})
    kwargs = {}
    for key, value in data.items():
        if key in retired and key not in fields:
            if value:  # an older file asked for the behaviour the key used to switch on
                warnings.warn(f"{where}.{key} is no longer a config key and is ignored: {retired[key]}", stacklevel=2)
            continue
        if key not in fields:
            raise ConfigError(_unknown_key_message(str(key), where, list(fields)))
        kwargs[key] = _convert(value, hints[key], f"{where}.{key}")
    missing = [
        name
        for name, f in fields.items()
        if name not in kwargs and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    ]
    if missing:
        raise ConfigError(f"{where}: missing required keys: {', '.join(missing)}")
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as error:
        if isinstance(error, ConfigError):
            raise
        raise ConfigError(f"{where}: {error}") from error


# ----------------------------------------------------------------------------------------------- ranges
def check_ranges(prefix: str, cfg: Any, ranges: Mapping[str, tuple[float, float]]) -> None:
    """Refuse a numeric field of ``cfg`` outside its inclusive ``(low, high)`` range.

    Every numeric setting has both bounds, physical or practical, so that a typo such as ``density=1e308`` or
    ``max_steps=-5`` is refused before any work instead of hanging, overflowing or doing nothing. Tuple fields are
    checked element by element. The message names ``prefix.field`` (e.g. ``train.max_steps``).
    """
    for name, (low, high) in ranges.items():
        value = getattr(cfg, name)
        for item in value if isinstance(value, tuple) else (value,):
            if not low <= item <= high:
                where = f"{prefix}.{name}" if prefix else name
                raise ConfigError(f"{where} must be between {_number(low)} and {_number(high)}, got {value!r}")


def check_magnitudes(prefix: str, cfg: Any, limit: float) -> None:
    """Refuse any number of ``cfg``, nested configs and tuples included, outside ``[-limit, limit]``.

    The coarse bound of a config whose fields have no ranges of their own (a model section): a value far past any
    that makes sense (``channels=10**12``) is refused before it is allocated. The message names ``prefix.a.b``.
    """
    for field in dataclasses.fields(cfg):
        value = getattr(cfg, field.name)
        where = f"{prefix}.{field.name}" if prefix else field.name
        if dataclasses.is_dataclass(value):
            check_magnitudes(where, value, limit)
            continue
        for item in value if isinstance(value, tuple) else (value,):
            if isinstance(item, (int, float)) and not isinstance(item, bool) and not -limit <= item <= limit:
                raise ConfigError(f"{where} must be between {_number(-limit)} and {_number(limit)}, got {value!r}")


def _number(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


# ----------------------------------------------------------------------------------------------- overrides
def _parse_override(override: str) -> tuple[list[str], Any]:
    key, sep, text = override.partition("=")
    if not sep or not key.strip():
        raise ConfigError(f"override {override!r} must look like key.sub=value")
    try:
        value = yaml.safe_load(text) if text.strip() else ""
    except yaml.YAMLError as error:
        raise ConfigError(f"override {override!r}: value is not valid YAML ({error})") from error
    return key.strip().split("."), value


def _set_path(data: dict, path: list[str], value: Any, override: str) -> None:
    node = data
    for depth, part in enumerate(path[:-1]):
        child = node.get(part) if isinstance(node, dict) else None
        if not isinstance(child, dict):
            prefix = ".".join(path[: depth + 1])
            if isinstance(node, dict) and part not in node:
                raise ConfigError(_unknown_key_message(part, f"override {override!r}", list(node)))
            raise ConfigError(f"override {override!r}: {prefix} is a value, not a section")
        node = child
    if path[-1] not in node:
        raise ConfigError(_unknown_key_message(path[-1], f"override {override!r}", list(node)))
    node[path[-1]] = value


def override_dict(data: dict, overrides: Sequence[str]) -> dict:
    """Apply dotted ``key.sub=value`` overrides in place to the plain-dict form of a config; keys must exist."""
    for override in overrides:
        path, value = _parse_override(override)
        _set_path(data, path, value, override)
    return data


def apply_overrides(cfg: C, overrides: Sequence[str]) -> C:
    """Return a copy of ``cfg`` with dotted ``key.sub=value`` overrides applied (values parsed as YAML).

    ``["optim.lr=2e-4", "data.cameras=[CAM_FRONT]"]``; every key must exist and every value is type-checked.
    """
    if not overrides:
        return cfg
    return from_dict(type(cfg), override_dict(to_dict(cfg), overrides), "config (after --set)")


# ----------------------------------------------------------------------------------------------- YAML files
def load_config(cls: type[C], path: str | Path, overrides: Sequence[str] = ()) -> C:
    """Read a YAML file into config ``cls``, then apply dotted overrides. Errors name the file and key."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as error:
        raise ConfigError(f"cannot read config {path}: {error.strerror}") from error
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise ConfigError(f"{path}: not valid YAML: {error}") from error
    cfg = from_dict(cls, data if data is not None else {}, str(path))
    return apply_overrides(cfg, overrides)


def dump_yaml(cfg: Any, comments: bool = True) -> str:
    """YAML text of a config; with ``comments`` each field's docstring is written above it."""
    if not comments:
        return yaml.safe_dump(to_dict(cfg), sort_keys=False)
    return "\n".join(_yaml_lines(cfg, indent=0)) + "\n"


def _yaml_lines(cfg: Any, indent: int) -> list[str]:
    pad = " " * indent
    docs = field_docs(type(cfg))
    lines = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        for doc_line in textwrap.wrap(docs.get(f.name, ""), 100):
            lines.append(f"{pad}# {doc_line}")
        if dataclasses.is_dataclass(value):
            lines.append(f"{pad}{f.name}:")
            lines.extend(_yaml_lines(value, indent + 2))
        else:
            # Flow style keeps each value on its field's line, under its comment.
            text = yaml.safe_dump(to_dict(value), default_flow_style=True, sort_keys=False, width=10**6)
            inline = text.removesuffix("...\n").strip()
            lines.append(f"{pad}{f.name}: {inline}")
    return lines


def save_config(cfg: Any, path: str | Path) -> Path:
    """Write a config as commented YAML; :func:`load_config` reads it back to an equal config."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(dump_yaml(cfg))
    return path


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The docstring written under each field of a dataclass (``{}`` where the source is unavailable)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError, SyntaxError):
            continue
        body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
        for node, following in zip(body, body[1:], strict=False):
            if (
                isinstance(node, ast.AnnAssign)
                and isinstance(node.target, ast.Name)
                and isinstance(following, ast.Expr)
                and isinstance(following.value, ast.Constant)
                and isinstance(following.value.value, str)
            ):
                docs[node.target.id] = " ".join(following.value.value.split())
    return docs


#: The side of a :func:`leaf_differences` entry where the key is absent.
MISSING = object()


def leaf_differences(first: Any, second: Any, key: str = "") -> list[tuple[str, Any, Any]]:
    """``(dotted key, first value, second value)`` of every leaf where two nested dicts differ, keys sorted; a side
    without the key holds :data:`MISSING`."""
    if isinstance(first, dict) and isinstance(second, dict):
        found = []
        for name in sorted(set(first) | set(second)):
            found += leaf_differences(first.get(name, MISSING), second.get(name, MISSING),
                                      f"{key}.{name}" if key else name)  # fmt: skip
        return found
    return [] if first == second else [(key, first, second)]
