"""Checkpoints: one safetensors file whose header metadata carries the model's JSON config.

Loading never unpickles: safetensors holds raw tensors only, and a Magic Leap ``.pth`` is read with
``torch.load(weights_only=True)``.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

from models.featurenet import FeatureNet, FeatureNetConfig
from models.superpoint import SuperPointConfig, SuperPointNet, load_superpoint_v1
from models.errors import CheckpointError
from vo_runtime.artefact import sha256_file
from vo_runtime.atomic_file import atomic_path
from vo_runtime.errors import first_line

CHECKPOINT_FORMAT = "edgefeat-checkpoint/1"
__all__ = ["CHECKPOINT_FORMAT", "CheckpointError", "CheckpointInfo", "build_model", "checkpoint_metadata",
           "load_checkpoint", "save_checkpoint"]


@dataclass
class CheckpointInfo:
    path: str
    sha256: str
    arch: str
    config: dict[str, Any]
    metadata: dict[str, Any]


def build_model(arch: str, config: dict[str, Any] | None = None) -> nn.Module:
    """Instantiate ``featurenet`` or ``superpoint`` from a plain config dict."""
    config = dict(config or {})
    if arch == "featurenet":
        return FeatureNet(FeatureNetConfig(**config))
    if arch == "superpoint":
        return SuperPointNet(SuperPointConfig(**config))
    raise CheckpointError(f"unknown architecture {arch!r} (expected featurenet or superpoint)")


def save_checkpoint(model: nn.Module, path: str | Path, metadata: dict[str, Any] | None = None) -> Path:
    """Write ``model`` to ``path`` (.safetensors) atomically: a temp file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {
        "format": CHECKPOINT_FORMAT,
        "arch": model.arch,
        "config": json.dumps(model.config.to_dict()),
        "metadata": json.dumps(metadata or {}),
    }
    tensors = {key: value.detach().cpu().contiguous() for key, value in model.state_dict().items()}
    with atomic_path(path) as temporary:
        save_file(tensors, str(temporary), metadata=header)
    return path


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            header = handle.metadata() or {}
        return load_file(str(path)), header
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path} is not a readable safetensors checkpoint ({first_line(exc)})") from None


def checkpoint_metadata(path: str | Path) -> dict[str, Any] | None:
    """The metadata of an EdgeFeat checkpoint file, or None for any other file (never raises)."""
    from safetensors import safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            header = handle.metadata() or {}
        if header.get("format") != CHECKPOINT_FORMAT:
            return None
        metadata = json.loads(header.get("metadata", "{}"))
    except (SafetensorError, OSError, ValueError):
        return None
    return metadata if isinstance(metadata, dict) else None


def _require_finite(tensors: dict[str, torch.Tensor], path: Path) -> None:
    """Weights with NaN or infinities give NaN scores, and the keypoint selection then indexes nothing: the
    checkpoint is refused when it is loaded, naming the first such tensor."""
    for name, tensor in tensors.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            raise CheckpointError(f"{path} holds NaN or infinite weights ({name}): it is damaged or diverged in "
                                  "training; use an earlier checkpoint")


def load_checkpoint(path: str | Path) -> tuple[nn.Module, CheckpointInfo]:
    """Load a ``.safetensors`` EdgeFeat checkpoint or a Magic Leap ``superpoint_v1.pth``; model in eval mode.

    Raises `CheckpointError` (exit 2 in the CLI) for a missing, corrupt or mismatched file.
    """
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"checkpoint {path} is a folder, not a checkpoint file")
    if not path.is_file():
        raise CheckpointError(f"checkpoint not found: {path}")
    if path.stat().st_size == 0:
        raise CheckpointError(f"checkpoint {path} is empty")
    digest = sha256_file(path)
    if path.suffix in (".pth", ".pt"):
        try:
            model = load_superpoint_v1(path)
        except (ValueError, RuntimeError, OSError) as exc:
            raise CheckpointError(f"cannot load {path}: {first_line(exc)}") from None
        _require_finite(model.state_dict(), path)
        return model, CheckpointInfo(str(path), digest, "superpoint", model.config.to_dict(), {"source": "superpoint_v1"})
    tensors, header = _read_safetensors(path)
    _require_finite(tensors, path)
    if header.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is a safetensors file but not an EdgeFeat checkpoint (no {CHECKPOINT_FORMAT} header)")
    try:
        config = json.loads(header["config"])
        metadata = json.loads(header.get("metadata", "{}"))
        model = build_model(header["arch"], config)
    except (KeyError, TypeError, ValueError, RecursionError) as exc:
        raise CheckpointError(f"{path} has a malformed config header ({first_line(exc)})") from None
    try:
        model.load_state_dict(tensors, strict=True)
    except RuntimeError as exc:
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()][:2]
        raise CheckpointError(f"{path} does not match its {header['arch']} config: {' '.join(lines)[:200]}") from None
    return model.eval(), CheckpointInfo(str(path), digest, header["arch"], config, metadata)
