"""Learned peers in the VO: XFeat and the teacher (ALIKE), as extractors `vo_runtime.VisualOdometry` takes, so
that bench/eval_vo.py runs them in the same pipeline and the same runs as ORB and the shipped artefact.

Bench only: both run in PyTorch (the runtime imports no torch). Each keeps its own detector and descriptor
(`toolkit.evaluation`'s adapters, as `toolkit eval --model xfeat / teacher:alike-n` runs them), capped at
`PEER_KEYPOINTS` a frame at the camera's own resolution; their descriptors are made unit-norm for the VO's
matcher, and their scores weigh nothing (as ORB's: what a peer's score says of its keypoint's error is
unmeasured).
"""
from __future__ import annotations

import numpy as np

from vo_runtime.features import Features, to_gray_u8

PEER_KEYPOINTS = 1024  # twice the shipped drone artefact's 512, half ORB's 2000: each peer's usual realtime range


def is_peer(features: str) -> bool:
    """Whether an eval_vo ``--features`` entry names a learned peer (``xfeat``, ``teacher:NAME``)."""
    return features == "xfeat" or features.startswith("teacher:")


class PeerExtractor:
    """A `toolkit eval` detector spec (``xfeat``, ``teacher:alike-n``) as a VO extractor, one torch thread."""

    def __init__(self, spec: str, keypoints: int = PEER_KEYPOINTS) -> None:
        import torch

        from toolkit.evaluation.detection import DetectorConfig
        from toolkit.evaluation.detectors import load_detector

        torch.set_num_threads(1)
        self.detector = load_detector(spec, DetectorConfig(max_keypoints=int(keypoints)))
        self.providers = ["torch-cpu"]

    def __call__(self, image: np.ndarray) -> Features:
        detection = self.detector(to_gray_u8(image))
        order = np.argsort(-detection.scores, kind="stable")
        descriptors = np.asarray(detection.descriptors, np.float32)[order]
        descriptors /= np.maximum(np.linalg.norm(descriptors, axis=1, keepdims=True), 1e-12)
        return Features(np.asarray(detection.keypoints, np.float32)[order],
                        np.asarray(detection.scores, np.float32)[order], descriptors, scores_predict_error=False)
