"""Parsing the HxW input sizes that every command takes."""
from __future__ import annotations

from toolkit.errors import ToolkitError


def parse_size(text: str) -> tuple[int, int]:
    """'240x320' -> (240, 320) as (height, width); both at least 16 and multiples of 8 (the detector's cell)."""
    try:
        height, width = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise ToolkitError(f"input size must look like HxW (e.g. 240x320), got {text!r}") from None
    if height < 16 or width < 16 or height % 8 or width % 8:
        raise ToolkitError(f"input size {height}x{width} must be at least 16x16 and divisible by 8")
    return height, width
