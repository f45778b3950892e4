"""Frame ranges and frame-numbered file names, as render farms write them.

A frame range (``--frames``) is a comma-separated list of items, each one frame ``1012``, a
range ``1001-1100`` (both ends included) or a stepped range ``1001-1100x4`` (1001, 1005, ...,
up to 1100). Frames are integers and may be negative (``-10-10``); the result is sorted and
without repeats.

A file name pattern (``-o shot.####.exr``) holds one frame placeholder: a run of ``#``
(the frame number padded with zeros to the run's length: ``####`` -> ``1001``, ``0012``) or
a printf-style ``%d`` / ``%04d``. Longer frame numbers are never truncated.
"""
from __future__ import annotations

import re
from pathlib import Path

__all__ = ["FrameSpecError", "MAX_FRAMES", "frame_path", "has_frame_token", "parse_frames"]

#: More frames than this in one range is refused (a typo such as ``1-100000000`` would
#: otherwise allocate and schedule millions of renders).
MAX_FRAMES = 1_000_000

_ITEM = re.compile(r"^(-?\d+)(?:-(-?\d+)(?:x(\d+))?)?$")
_TOKEN = re.compile(r"#+|%(0\d+)?d")


class FrameSpecError(ValueError):
    """A frame range or output pattern that cannot be used (the message is one line)."""


def parse_frames(text: str) -> list[int]:
    """The frames of a range such as ``1001-1100``, ``1001-1100x2`` or ``1,5,10-20x5``."""
    spec = str(text).strip()
    if not spec:
        raise FrameSpecError("empty frame range: expected FIRST-LAST[xSTEP], e.g. 1001-1100 or 1001-1100x2")
    frames: set[int] = set()
    for raw in spec.split(","):
        item = raw.strip().replace(" ", "")
        m = _ITEM.match(item)
        if m is None:
            raise FrameSpecError(f"bad frame range {item!r} in {spec!r}: expected FIRST, FIRST-LAST "
                                 f"or FIRST-LASTxSTEP with integer frames (e.g. 1001-1100x2)")
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) is not None else first
        step = int(m.group(3)) if m.group(3) is not None else 1
        if step < 1:
            raise FrameSpecError(f"bad frame range {item!r}: the step must be >= 1")
        if last < first:
            raise FrameSpecError(f"empty frame range {item!r}: the last frame is before the first")
        count = (last - first) // step + 1
        if count + len(frames) > MAX_FRAMES:
            raise FrameSpecError(f"frame range {spec!r} has more than {MAX_FRAMES} frames")
        frames.update(range(first, last + 1, step))
    return sorted(frames)


def has_frame_token(pattern: str | Path) -> bool:
    """Whether the file name of ``pattern`` holds a frame placeholder (``####`` or ``%04d``)."""
    return _TOKEN.search(Path(pattern).name) is not None


def frame_path(pattern: str | Path, frame: int) -> Path:
    """``pattern`` with its frame placeholder replaced by ``frame`` (``shot.####.exr`` -> ``shot.1001.exr``).

    The placeholder must be in the file name, and there must be exactly one.
    """
    p = Path(pattern)
    if len(_TOKEN.findall(p.name)) != 1 or _TOKEN.search(str(p.parent)):
        raise FrameSpecError(f"output {str(pattern)!r}: expected one frame placeholder (#### or %04d) "
                             f"in the file name, e.g. shot.####.exr")

    def number(m: re.Match[str]) -> str:
        tok = m.group(0)
        width = len(tok) if tok.startswith("#") else int(m.group(1) or "0")
        return f"{int(frame):0{width}d}"

    return p.with_name(_TOKEN.sub(number, p.name, count=1))
