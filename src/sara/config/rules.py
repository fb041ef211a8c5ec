"""The valid values of the options, and `option()`, which writes a field with its rule beside it.

Every field of every section is made by `option(default, rule, doc, advanced=...)`: its default,
the check of its valid values, whether it is an everyday or an advanced key, and what it does, in
one place. `validate` runs the checks when a section is made, so a bad `-s key=value` fails at once,
naming the option and its valid range. This module imports nothing of sara.
"""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Callable
from typing import Any

import numpy as np

Check = Callable[[Any], bool]
#: (check, description of the valid values)
Rule = tuple[Check, str]

#: COLMAP's camera models (pycolmap.CameraModelId, less INVALID)
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "SIMPLE_RADIAL_FISHEYE", "RADIAL", "RADIAL_FISHEYE",
    "OPENCV", "OPENCV_FISHEYE", "FULL_OPENCV", "FOV", "THIN_PRISM_FISHEYE", "RAD_TAN_THIN_PRISM_FISHEYE",
    "SIMPLE_DIVISION", "DIVISION", "SIMPLE_FISHEYE", "FISHEYE", "EUCM", "EQUIRECTANGULAR",
)
MAX_SEED = 2**31 - 1


class ConfigError(ValueError):
    """An option has a value outside its valid range; `option` is its dotted name."""

    def __init__(self, option: str, message: str) -> None:
        super().__init__(message)
        self.option = option


def option(default: Any = dataclasses.MISSING, rule: Rule | None = None, doc: str = "", *,
           advanced: bool = True, factory: Callable[[], Any] | None = None) -> Any:
    """A dataclass field with its rule, its everyday/advanced flag and its description beside it."""
    if rule is None:
        raise TypeError("every option needs a rule")
    metadata = {"rule": rule, "advanced": advanced, "doc": " ".join(doc.split())}
    if factory is not None:
        return dataclasses.field(default_factory=factory, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def validate(conf: Any) -> None:
    """Raise ConfigError for the first field of a config section outside its valid range."""
    section = getattr(type(conf), "SECTION", type(conf).__name__)
    for f in dataclasses.fields(conf):
        value = getattr(conf, f.name)
        if dataclasses.is_dataclass(value):
            continue
        name = f"{section}.{f.name}" if section else f.name
        rule = f.metadata.get("rule")
        if rule is not None and not rule[0](value):
            raise ConfigError(name, f"{name} must be {rule[1]}, got {value!r}")


def _is_int(value: Any) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _is_real(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def ints(low: int, high: int | None = None) -> Rule:
    text = f"an integer >= {low}" if high is None else f"an integer from {low} to {high}"
    return (lambda v: _is_int(v) and v >= low and (high is None or v <= high)), text


def reals(low: float, high: float | None = None, *, low_open: bool = False, high_open: bool = False) -> Rule:
    def ok(v: Any) -> bool:
        if not _is_real(v) or not math.isfinite(v):
            return False
        above = v > low if low_open else v >= low
        below = high is None or (v < high if high_open else v <= high)
        return above and below

    if high is None:
        text = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        text = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"
    return ok, text


def choice(*options: str) -> Rule:
    return (lambda v: v in options), "one of " + ", ".join(options)


def name() -> Rule:
    return (lambda v: isinstance(v, str) and v.strip() != "" and v == v.strip()), "a name (not empty)"


def text() -> Rule:
    return (lambda v: isinstance(v, str)), "a string"


def flag() -> Rule:
    return (lambda v: isinstance(v, (bool, np.bool_))), "true or false"


def device() -> Rule:
    return (lambda v: isinstance(v, str) and re.fullmatch(r"auto|cpu|mps|cuda(:\d+)?", v) is not None,
            "auto, cpu, cuda, cuda:N or mps")


def numbers_list() -> Rule:
    def ok(v: Any) -> bool:
        if not isinstance(v, str):
            return False
        if not v.strip():
            return True
        try:
            return all(math.isfinite(float(x)) for x in v.split(","))
        except ValueError:
            return False

    return ok, "empty or comma-separated numbers, e.g. 1200,1200,512,384"


def shares(count: int) -> Rule:
    """`count` non-negative numbers with a positive sum (shares of a budget, normalised later)."""
    def ok(v: Any) -> bool:
        try:
            values = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            return False
        return values.shape == (count,) and bool(np.all(values >= 0)) and bool(values.sum() > 0)

    return ok, f"{count} non-negative numbers with a positive sum, e.g. 0.5,0.25,0.25"


def growth() -> Rule:
    """0 (chosen by the scene's size) or a growth factor above 1."""
    return (lambda v: _is_real(v) and math.isfinite(v) and (v == 0 or v > 1)), "0 (by size) or a number > 1"


def threads() -> Rule:
    """COLMAP's thread count: -1 (or 0) uses every core."""
    return ints(-1)
