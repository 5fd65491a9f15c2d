"""What `toolkit profile --model` accepts: an architecture name, a checkpoint, or an artefact directory.

Architecture names build the network with random weights (seed 0): counts and latency do not depend
on weight values, so an untrained network profiles exactly like a trained one.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import onnx
import torch
from torch import nn

from models.checkpoint import build_model, load_checkpoint
from models.featurenet import FeatureNet, FeatureNetConfig
from models.superpoint import SuperPointNet
from toolkit.errors import ToolkitError
from export.artefact_graph import load_artefact_graph
from vo_runtime.errors import first_line

ARCHITECTURES = ("featurenet", "featurenet-relu", "superpoint")


@dataclass
class ModelSource:
    """A network to profile, and the artefact it came from if any."""

    name: str
    net: nn.Module
    origin: str  # "architecture (random weights)", "checkpoint PATH" or "artefact DIR"
    artefact_dir: Path | None = None
    artefact_target: str | None = None
    artefact_size: tuple[int, int] | None = None
    artefact_dense: bool = False
    max_keypoints: int | None = None
    nms_radius: int = 4
    threshold: float = 0.005
    border: int = 4
    graph: onnx.ModelProto | None = None  # an artefact's graph, loaded and checked once (`load_artefact_graph`)

    def artefact_model(self) -> onnx.ModelProto:
        assert self.graph is not None
        return self.graph


def architecture(name: str) -> nn.Module:
    """A named architecture with random (seeded) weights, in eval mode."""
    torch.manual_seed(0)
    if name == "featurenet":
        return FeatureNet().eval()
    if name == "featurenet-relu":
        return FeatureNet(FeatureNetConfig(activation="relu")).eval()
    if name == "superpoint":
        return SuperPointNet().eval()
    raise ToolkitError(f"unknown model {name!r}: use {', '.join(ARCHITECTURES)}, a checkpoint file or an artefact directory")


def resolve_model(spec: str, requested_size: tuple[int, int] | None) -> ModelSource:
    """Turn one ``--model`` value into a `ModelSource`; an artefact must match ``requested_size`` if given."""
    from models.weights import ALIASES, resolve_checkpoint

    path = Path(spec)
    if spec in ARCHITECTURES:
        return ModelSource(spec, architecture(spec), "architecture (random weights)")
    if spec in ALIASES and not path.exists():
        net, info = load_checkpoint(resolve_checkpoint(spec))
        return ModelSource(f"{ALIASES[spec]} (shipped)", net, f"shipped weights {info.path}")
    if path.is_dir():
        return _from_artefact(path, requested_size)
    if path.is_file():
        net, info = load_checkpoint(path)
        label = f"{path.stem} ({info.arch})"
        return ModelSource(label, net, f"checkpoint {path}")
    raise ToolkitError(f"unknown model {spec!r}: use default, default-relu, {', '.join(ARCHITECTURES)}, a checkpoint "
                       "file or an artefact directory")


def _from_artefact(directory: Path, requested_size: tuple[int, int] | None) -> ModelSource:
    manifest, graph = load_artefact_graph(directory)  # ArtefactError: one line, exit 2
    shape = manifest["input"]["shape"]
    size = (int(shape[2]), int(shape[3]))
    if requested_size is not None and size != tuple(requested_size):
        raise ToolkitError(
            f"artefact {directory} was exported for {size[0]}x{size[1]}, not {requested_size[0]}x{requested_size[1]} "
            "as asked: re-export it at that size or drop --input-size"
        )
    model = manifest.get("model", {})
    # The artefact holds the graph; a same-architecture network (random weights) stands in for the
    # PyTorch-side count and the eager reference timing, which do not depend on weight values.
    try:
        net = build_model(model.get("arch", ""), model.get("config") or {}).eval()
    except (TypeError, ValueError) as exc:  # a manifest whose model config no network accepts
        raise ToolkitError(f"artefact {directory}: its manifest's model config is unusable ({first_line(exc)})") from None
    post = manifest.get("postprocess", {})
    return ModelSource(
        name=f"{directory.name} ({model.get('arch', '?')})",
        net=net,
        origin=f"artefact {directory}",
        artefact_dir=directory,
        artefact_target=str(manifest.get("target")),
        artefact_size=size,
        artefact_dense=manifest.get("mode") == "dense",
        max_keypoints=post.get("max_keypoints"),
        nms_radius=int(post.get("nms_radius", 4)),
        threshold=float(post.get("detection_threshold", 0.005)),
        border=int(post.get("border", 4)),
        graph=graph,
    )
