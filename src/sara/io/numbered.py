"""Numbered names: the frames of one sequence (a video's frames as ffmpeg or sara writes them, a
burst, a drive) share a name but for the last run of digits before the extension."""

from __future__ import annotations

import re

#: (anything)(the last run of digits)(no digit up to the end): the frame number of a name
FRAME_NUMBER = re.compile(r"^(?P<prefix>.*?)(?P<number>\d+)(?P<suffix>\D*)$")


def numbered(name: str) -> tuple[tuple[str, str], int] | None:
    """((what the frames of `name`'s sequence share: the name before and after the number, the
    extension in lower case), its frame number), or None for a name without digits."""
    stem, dot, ext = name.rpartition(".")
    match = FRAME_NUMBER.match(stem if dot else name)
    if match is None:
        return None
    return (match["prefix"], match["suffix"] + (dot + ext.lower() if dot else "")), int(match["number"])
