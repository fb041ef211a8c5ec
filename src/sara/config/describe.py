"""docs/configuration.md, generated from the fields: everyday keys first, then the advanced ones."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from typing import Any

from .layout import RENAMED, PipelineConfig, sections
from .presets import PRESETS

REGENERATE = ('python -c "from sara.config import describe_markdown; '
              "open('docs/configuration.md', 'w').write(describe_markdown())\"")


@dataclasses.dataclass(frozen=True)
class KeyInfo:
    """One option as the documentation shows it."""

    key: str  # "section.field" ("seed" at the top level)
    default: Any
    valid: str
    doc: str
    advanced: bool


def keys() -> Iterator[KeyInfo]:
    """Every option of `PipelineConfig`, in its order."""
    defaults = PipelineConfig()
    for section in sections():
        conf = getattr(defaults, section)
        for f in dataclasses.fields(conf):
            yield _info(f"{section}.{f.name}", f, getattr(conf, f.name))
    seed = next(f for f in dataclasses.fields(PipelineConfig) if f.name == "seed")
    yield _info("seed", seed, defaults.seed)


def _info(key: str, f: dataclasses.Field, default: Any) -> KeyInfo:
    return KeyInfo(key, default, f.metadata["rule"][1], f.metadata["doc"], f.metadata["advanced"])


def everyday_keys() -> list[str]:
    """The options most users set; the others are the paper's constants and experiment knobs."""
    return [k.key for k in keys() if not k.advanced]


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "`true`" if value else "`false`"
    if isinstance(value, float):
        text = f"{value:g}"
        return f"`{text}`" if any(c in text for c in ".en") else f"`{text}.0`"
    if isinstance(value, tuple):
        return "`" + ",".join(_value(v).strip("`") for v in value) + "`"
    if value == "":
        return '`""` (empty)'
    return f"`{value}`"


def _table(rows: list[KeyInfo]) -> list[str]:
    out = ["| key | default | valid values | what it does |", "| --- | --- | --- | --- |"]
    for row in rows:
        cells = [f"`{row.key}`", _value(row.default), row.valid, row.doc]
        out.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return out


def describe_markdown() -> str:
    """The configuration reference as Markdown (docs/configuration.md is this text)."""
    all_keys = list(keys())
    lines = ["# Configuration", "",
             "<!-- Generated from src/sara/config; do not edit. Regenerate with:",
             f"     {REGENERATE} -->", "",
             "Every run takes a preset (`--preset NAME`: "
             + ", ".join(f"`{name}`" for name in PRESETS)
             + ") plus `-s section.key=value` overrides, and writes the resolved configuration to "
             "`run.json` in its output folder. An unknown key is an error that lists the valid ones.", "",
             "## Everyday keys", ""]
    lines += _table([k for k in all_keys if not k.advanced])
    lines += ["", "## Advanced keys", "",
              "The paper's constants and the knobs of experiments: their defaults are the measured ones.", ""]
    defaults = PipelineConfig()
    for section in sections():
        rows = [k for k in all_keys if k.advanced and k.key.startswith(section + ".")]
        if rows:
            lines += [f"### {section}", "", _summary(getattr(defaults, section)), ""] + _table(rows) + [""]
    lines += ["## Renamed keys", "",
              "These old names still work (with a warning), on the command line and in old `run.json` files.", "",
              "| old key | new key |", "| --- | --- |"]
    lines += [f"| `{old}` | `{new}` |" for old, new in RENAMED.items()]
    return "\n".join(lines) + "\n"


def _summary(conf: Any) -> str:
    return " ".join((type(conf).__doc__ or "").strip().split("\n\n")[0].split())
