"""The SuperPoint architecture (DeTone et al., CVPRW 2018): VGG-style encoder, 1.3 M parameters.

Parameter names follow Magic Leap's released ``superpoint_v1.pth`` (conv1a ... conv4b, convPa/convPb,
convDa/convDb; no batch norm), so a user's copy of those weights loads with strict key matching.
Used as a teacher and as the comparison baseline.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from models.torch_files import load_weights_only


@dataclass
class SuperPointConfig:
    descriptor_dim: int = 256

    def to_dict(self) -> dict:
        return asdict(self)


class SuperPointNet(nn.Module):
    """forward(image [B, 1, H, W] gray in [0, 1]) -> {"logits": [B, 65, H/8, W/8], "descriptors": [B, D, H/8, W/8]}."""

    arch = "superpoint"

    def __init__(self, config: SuperPointConfig | None = None) -> None:
        super().__init__()
        self.config = config or SuperPointConfig()
        widths = (64, 64, 128, 128)
        self.conv1a = nn.Conv2d(1, widths[0], 3, padding=1)
        self.conv1b = nn.Conv2d(widths[0], widths[0], 3, padding=1)
        self.conv2a = nn.Conv2d(widths[0], widths[1], 3, padding=1)
        self.conv2b = nn.Conv2d(widths[1], widths[1], 3, padding=1)
        self.conv3a = nn.Conv2d(widths[1], widths[2], 3, padding=1)
        self.conv3b = nn.Conv2d(widths[2], widths[2], 3, padding=1)
        self.conv4a = nn.Conv2d(widths[2], widths[3], 3, padding=1)
        self.conv4b = nn.Conv2d(widths[3], widths[3], 3, padding=1)
        self.convPa = nn.Conv2d(widths[3], 256, 3, padding=1)
        self.convPb = nn.Conv2d(256, 65, 1)
        self.convDa = nn.Conv2d(widths[3], 256, 3, padding=1)
        self.convDb = nn.Conv2d(256, self.config.descriptor_dim, 1)

    def forward(self, image: torch.Tensor) -> dict[str, torch.Tensor]:
        x = F.relu(self.conv1b(F.relu(self.conv1a(image))))
        x = F.max_pool2d(x, 2, 2)
        x = F.relu(self.conv2b(F.relu(self.conv2a(x))))
        x = F.max_pool2d(x, 2, 2)
        x = F.relu(self.conv3b(F.relu(self.conv3a(x))))
        x = F.max_pool2d(x, 2, 2)
        x = F.relu(self.conv4b(F.relu(self.conv4a(x))))
        logits = self.convPb(F.relu(self.convPa(x)))
        descriptors = F.normalize(self.convDb(F.relu(self.convDa(x))), p=2.0, dim=1)
        return {"logits": logits, "descriptors": descriptors}


def load_superpoint_v1(path: str | Path) -> SuperPointNet:
    """Load Magic Leap's ``superpoint_v1.pth`` (a plain state dict) without unpickling arbitrary objects.

    Raises ``ValueError`` for an unreadable file, missing/unexpected keys or a shape mismatch.
    """
    state = load_weights_only(path)
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path} does not hold a state dict")
    model = SuperPointNet()
    expected = model.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    if missing or unexpected:
        raise ValueError(f"{path} is not a superpoint_v1 state dict (missing {missing[:3]}, unexpected {unexpected[:3]})")
    for key, tensor in expected.items():
        if tuple(state[key].shape) != tuple(tensor.shape):
            raise ValueError(f"{path}: {key} has shape {tuple(state[key].shape)}, expected {tuple(tensor.shape)}")
    model.load_state_dict(state, strict=True)
    return model.eval()
