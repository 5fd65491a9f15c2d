"""Shared check for grown or pruned FeatureNets: saved, loaded and exported to both targets, same outputs."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from export.artefact import ExportOptions, export_artefact
from models.checkpoint import load_checkpoint, save_checkpoint
from vo_runtime.artefact import verify_artefact


def assert_saves_and_exports(model: torch.nn.Module, images: np.ndarray, folder: Path, size: tuple[int, int]) -> dict:
    """Save ``model``, check the loaded copy computes the same logits on ``images[:1]``, export it for x86-cpu
    and tx2 and check each artefact's parity; return the saved checkpoint's config."""
    path = save_checkpoint(model, folder / "model.safetensors")
    loaded, info = load_checkpoint(path)
    x = torch.from_numpy(np.ascontiguousarray(images[:1]))
    with torch.no_grad():
        assert torch.allclose(loaded.eval()(x)["logits"], model.eval()(x)["logits"], atol=1e-5)
    for target in ("x86-cpu", "tx2"):
        out = export_artefact(ExportOptions(target=target, output=folder / target, checkpoint=path,
                                            input_size=size, precision="fp32"), log=lambda _m: None)
        assert verify_artefact(out)["parity"]["keypoints_identical"] >= 0.99
    return info.config
