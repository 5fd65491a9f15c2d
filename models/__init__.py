"""Networks: FeatureNet (depthwise-separable + deformable), the SuperPoint architecture, checkpoints."""
from models.featurenet import FeatureNet, FeatureNetConfig
from models.superpoint import SuperPointNet, load_superpoint_v1

__all__ = ["FeatureNet", "FeatureNetConfig", "SuperPointNet", "load_superpoint_v1"]
