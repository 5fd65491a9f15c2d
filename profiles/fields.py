"""Typed reading of a profile's TOML table: each field has one type and range, checked when the profile is
loaded, so a bad value is one error naming the field instead of a crash (or a NaN figure) deep inside an
export or a profile run."""
from __future__ import annotations

import math
from typing import Any

from profiles.errors import ProfileError

# ONNX opsets the exporter can write: DeformConv-free graphs need 11 (the portable gathers), onnx knows 23.
MIN_OPSET, MAX_OPSET = 11, 23
MIN_SIDE, MAX_SIDE = 16, 4096  # the network input sides every command accepts (toolkit.sizes)
MAX_KEYPOINTS = 1 << 20
PRECISIONS = ("fp32", "fp16", "int8")


class Fields:
    """Readers of one profile table; every error names the file and the dotted field."""

    def __init__(self, table: dict[str, Any], source: str) -> None:
        self.table, self.source = table, source

    def error(self, dotted: str, what: str, value: Any) -> ProfileError:
        return ProfileError(f"profile {self.source}: {dotted} must be {what}, got {value!r}")

    def get(self, dotted: str) -> Any:
        node: Any = self.table
        for part in dotted.split("."):
            if not isinstance(node, dict) or part not in node:
                raise ProfileError(f"profile {self.source} is missing the field '{dotted}'")
            node = node[part]
        return node

    def text(self, dotted: str, choices: tuple[str, ...] | None = None) -> str:
        value = self.get(dotted)
        if not isinstance(value, str) or not value.strip():
            raise self.error(dotted, "a non-empty string", value)
        if choices is not None and value not in choices:
            raise self.error(dotted, f"one of {', '.join(choices)}", value)
        return value

    def whole(self, dotted: str, low: int, high: int) -> int:
        value = self.get(dotted)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise self.error(dotted, f"a whole number from {low} to {high}", value)
        return value

    def wholes(self, dotted: str, low: int, high: int) -> tuple[int, ...]:
        value = self.get(dotted)
        if not isinstance(value, list) or not all(isinstance(v, int) and not isinstance(v, bool) and low <= v <= high
                                                  for v in value):
            raise self.error(dotted, f"a list of whole numbers from {low} to {high}", value)
        return tuple(sorted(set(value)))

    def texts(self, dotted: str, choices: tuple[str, ...] | None = None, empty: bool = True) -> tuple[str, ...]:
        value = self.get(dotted)
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value) or (not empty and not value):
            raise self.error(dotted, "a list of strings" + ("" if empty else " (at least one)"), value)
        unknown = [v for v in value if choices is not None and v not in choices]
        if unknown:
            raise self.error(dotted, f"a list of {', '.join(choices)}", value)
        return tuple(value)

    def input_size(self, dotted: str) -> tuple[int, int]:
        value = self.get(dotted)
        sides_ok = isinstance(value, list) and len(value) == 2 and all(
            isinstance(v, int) and not isinstance(v, bool) and MIN_SIDE <= v <= MAX_SIDE and v % 8 == 0 for v in value)
        if not sides_ok:
            raise self.error(dotted, f"[height, width], whole multiples of 8 from {MIN_SIDE} to {MAX_SIDE}", value)
        return int(value[0]), int(value[1])

    def table_of(self, dotted: str, required: bool = False) -> dict[str, Any]:
        try:
            value = self.get(dotted)
        except ProfileError:
            if required:
                raise
            return {}
        if not isinstance(value, dict):
            raise self.error(dotted, "a table", value)
        return value


def check_finite_numbers(value: Any, dotted: str, source: str) -> None:
    """Every number under ``value`` finite: a NaN or infinite figure would end as invalid JSON in a report."""
    if isinstance(value, dict):
        for key, item in value.items():
            check_finite_numbers(item, f"{dotted}.{key}", source)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            check_finite_numbers(item, f"{dotted}[{index}]", source)
    elif isinstance(value, float) and not math.isfinite(value):
        raise ProfileError(f"profile {source}: {dotted} must be a finite number, got {value}")
