"""vo_runtime: a minimal monocular VO that runs an exported EdgeFeat artefact.

Depends on numpy, OpenCV and onnxruntime only (no torch).
"""
from vo_runtime.errors import ArtefactError, VORuntimeError
from vo_runtime.features import FeatureExtractor, Features

__all__ = ["ArtefactError", "FeatureExtractor", "Features", "VORuntimeError"]
