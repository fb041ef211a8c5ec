"""Overrides (`-s section.key=value`), presets and run.json: how a `PipelineConfig` is made."""

from __future__ import annotations

import dataclasses
import logging
import types
import typing
from typing import Any

from .layout import RENAMED, PipelineConfig
from .presets import PRESETS

logger = logging.getLogger(__name__)


def _parse_value(raw: str, typ: Any, key: str) -> Any:
    """`raw` (command-line text) as a value of the field type `typ` (its annotation, a string)."""
    if isinstance(typ, str) and typ.startswith("tuple["):  # "0.5,0.25,0.25" or "(0.5, 0.25, 0.25)"
        item = typ[len("tuple["):].split(",")[0].strip().rstrip("]")
        parts = [p for p in raw.strip().strip("()[]").split(",") if p.strip()]
        return tuple(_parse_value(p.strip(), item, key) for p in parts)
    if isinstance(typ, str):
        typ = {"int": int, "float": float, "bool": bool, "str": str}.get(typ, str)
    origin = typing.get_origin(typ)
    if origin in (typing.Union, types.UnionType):
        typ = next(t for t in typing.get_args(typ) if t is not type(None))
    try:
        if typ is bool:
            low = raw.strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(raw)
        if typ in (int, float, str):
            return typ(raw)
    except ValueError:
        raise ValueError(f"bad value for {key}: {raw!r} is not a {typ.__name__}") from None
    return raw


def _typed_value(value: Any, typ: Any, key: str) -> Any:
    """A value from the command line parsed by the field's type; a list (JSON) for a tuple field as a tuple."""
    if isinstance(value, str):
        return _parse_value(value, typ, key)
    if isinstance(value, list) and isinstance(typ, str) and typ.startswith("tuple["):
        return tuple(value)
    return value


def renamed_keys(overrides: dict[str, Any], *, warn: bool = True) -> dict[str, Any]:
    """`overrides` with every old key (`RENAMED`) under its new name; a warning names each new key."""
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        new = RENAMED.get(key)
        if new is None:
            out[key] = value
            continue
        if new in overrides:
            raise ValueError(f"option {key!r} is the old name of {new!r}: set only {new!r}")
        if warn:
            logger.warning("option %r is now called %r; the old name will go", key, new)
        out[new] = value
    return out


def apply_overrides(conf: Any, overrides: dict[str, Any], prefix: str = "") -> Any:
    """Return a copy of a (nested) config dataclass with `a.b=value` overrides applied.

    Values may be strings (from the command line; parsed by the field's type) or typed values.
    On a `PipelineConfig`, the old names of renamed keys (`RENAMED`) work too, with a warning.
    """
    if isinstance(conf, PipelineConfig) and not prefix:
        overrides = renamed_keys(overrides)
    fields = {f.name: f for f in dataclasses.fields(conf)}
    nested: dict[str, dict[str, Any]] = {}
    direct: dict[str, Any] = {}
    for key, value in overrides.items():
        head, _, rest = key.partition(".")
        if head not in fields:
            valid = ", ".join(prefix + n for n in fields)
            raise ValueError(f"unknown option {prefix + key!r}; valid options here: {valid}")
        current = getattr(conf, head)
        if rest:
            if not dataclasses.is_dataclass(current):
                raise ValueError(f"option {prefix + head!r} has no sub-options")
            nested.setdefault(head, {})[rest] = value
        elif dataclasses.is_dataclass(current):
            valid = ", ".join(f"{prefix}{head}.{f.name}" for f in dataclasses.fields(current))
            raise ValueError(f"{prefix + head!r} is a group of options: set one of {valid}")
        else:
            direct[head] = _typed_value(value, fields[head].type, prefix + key)
    for head, sub in nested.items():
        direct[head] = apply_overrides(getattr(conf, head), sub, prefix=f"{prefix}{head}.")
    return dataclasses.replace(conf, **direct)


def parse_override_args(args: list[str]) -> dict[str, str]:
    """`['a.b=1', 'c=x']` -> {'a.b': '1', 'c': 'x'}."""
    out = {}
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep or not key:
            raise ValueError(f"bad option {arg!r}: write it as key=value, e.g. retrieval.num_neighbors=20")
        out[key.strip()] = value.strip()
    return out


def make_config(preset: str = "sift-offline", overrides: dict[str, Any] | None = None) -> PipelineConfig:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose one of: {', '.join(PRESETS)}")
    conf = apply_overrides(PipelineConfig(), dict(PRESETS[preset]))
    return apply_overrides(conf, overrides or {})


def config_from_dict(data: dict[str, Any]) -> PipelineConfig:
    """Rebuild a PipelineConfig from `to_dict()` output (e.g. run.json), the old layout included."""
    flat: dict[str, Any] = {}

    def walk(d: dict[str, Any], prefix: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{prefix}{k}.")
            else:
                flat[prefix + k] = v

    walk(data, "")
    old = sorted(k for k in flat if k in RENAMED)
    if old:
        logger.info("configuration with %d options under their old names (e.g. %s): read as the new ones",
                    len(old), old[0])
    return apply_overrides(PipelineConfig(), renamed_keys(flat, warn=False))
