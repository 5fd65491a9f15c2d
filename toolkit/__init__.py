"""EdgeFeat toolkit: train, export, profile and evaluate a keypoint network for edge targets."""

__version__ = "0.1.0"
