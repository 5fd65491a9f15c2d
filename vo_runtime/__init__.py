"""vo_runtime: a minimal monocular VO that runs an exported EdgeFeat artefact.

Depends on numpy, OpenCV, onnxruntime and scipy (bundle adjustment); never on torch.
"""
from vo_runtime.camera import Camera, load_camera
from vo_runtime.errors import (ArtefactError, CalibrationError, ConcurrentUseError, FrameError, TimestampError,
                               VORuntimeError)
from vo_runtime.features import FeatureExtractor, Features, OrbExtractor
from vo_runtime.odometry import MonoVO, VisualOdometry, VOConfig, VOResult
from vo_runtime.pipeline import StreamFrame
from vo_runtime.trajectory import write_trajectory

__all__ = [
    "ArtefactError", "CalibrationError", "Camera", "ConcurrentUseError", "FeatureExtractor", "Features", "FrameError",
    "MonoVO", "OrbExtractor", "StreamFrame", "TimestampError", "VOConfig", "VOResult", "VORuntimeError",
    "VisualOdometry", "load_camera", "write_trajectory",
]
