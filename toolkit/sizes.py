"""Parsing the HxW input sizes that every command takes, bounded before anything is allocated."""
from __future__ import annotations

import re

# A 4096x4096 network input already needs gigabytes of activations; a larger one ends in an out-of-memory
# crash long after the command started, so it is refused up front (the profiles' bounds: one pair for all).
from profiles.fields import MAX_SIDE, MIN_SIDE
from toolkit.errors import ToolkitError


def parse_hxw(text: str, option: str = "--size") -> tuple[int, int]:
    """'240x320' -> (240, 320) as (height, width), each side in [MIN_SIDE, MAX_SIDE]; no other rule."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not match:
        raise ToolkitError(f"{option} must look like HxW (e.g. 240x320), got {text!r}")
    height, width = int(match.group(1)), int(match.group(2))
    if not (MIN_SIDE <= height <= MAX_SIDE and MIN_SIDE <= width <= MAX_SIDE):
        raise ToolkitError(f"{option} {height}x{width}: each side must be between {MIN_SIDE} and {MAX_SIDE} pixels")
    return height, width


def parse_size(text: str, option: str = "--size") -> tuple[int, int]:
    """A network input size: `parse_hxw`, and both sides multiples of 8 (the detector's cell)."""
    height, width = parse_hxw(text, option)
    if height % 8 or width % 8:
        raise ToolkitError(f"{option} {height}x{width}: both sides must be divisible by 8")
    return height, width
