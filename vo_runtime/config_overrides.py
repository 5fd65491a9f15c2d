"""`VOConfig` from ``FIELD=VALUE`` strings (the vo command's ``--set``): a knob changed without code, checked
before any frame is read.

``VALUE`` is JSON (``100``, ``0.5``, ``true``, ``null``); ``mapping.FIELD`` names a `MappingConfig` field. A field
that does not exist, a value that is not JSON or not of the field's type raises `VORuntimeError` naming it, so a
typo never runs a whole sequence with the default it meant to change.
"""
from __future__ import annotations

import json
from dataclasses import fields, replace
from typing import Any

from vo_runtime.config import VOConfig
from vo_runtime.errors import VORuntimeError


def _checked(owner: Any, name: str, text: str, item: str) -> Any:
    """The JSON ``text`` as a value for field ``name`` of dataclass instance ``owner``."""
    known = {f.name: f for f in fields(owner)}
    if name not in known or name == "mapping":
        choices = ", ".join(sorted(n for n in known if n != "mapping"))
        raise VORuntimeError(f"--set {item}: {type(owner).__name__} has no field {name!r} (fields: {choices})")
    try:
        value = json.loads(text)
    except json.JSONDecodeError:
        raise VORuntimeError(f"--set {item}: the value is not JSON (e.g. 100, 0.5, true, null)") from None
    default = getattr(owner, name)
    optional = "None" in str(known[name].type)
    if value is None and optional:
        return None
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
    else:
        ok = False
    if not ok:
        kind = {bool: "true or false", int: "an integer", float: "a number"}.get(type(default), "no value")
        raise VORuntimeError(f"--set {item}: {name} takes {kind}{' or null' if optional else ''}, got {text}")
    return value


def config_from_overrides(items: list[str], **given: Any) -> tuple[VOConfig, dict[str, Any]]:
    """`VOConfig(**given)` with each ``FIELD=VALUE`` of ``items`` applied; returns it and the overrides applied
    (field -> value, for the run's summary)."""
    config = VOConfig(**given)
    top: dict[str, Any] = {}
    mapping: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise VORuntimeError(f"--set {item}: expected FIELD=VALUE (e.g. init_wanted_landmarks=100)")
        if key.startswith("mapping."):
            mapping[key.split(".", 1)[1]] = _checked(config.mapping, key.split(".", 1)[1], text, item)
        else:
            top[key] = _checked(config, key, text, item)
    config = replace(config, **top, mapping=replace(config.mapping, **mapping))  # __post_init__ checks ranges
    applied = {**top, **{f"mapping.{k}": v for k, v in mapping.items()}}
    return config, applied
