"""EdgeFeat toolkit: train, export, profile and evaluate a keypoint network for edge targets."""

from vo_runtime.version import __version__  # one version for the toolkit and the runtime (CHANGELOG.md)

__all__ = ["__version__"]
