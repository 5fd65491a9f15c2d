"""Shared fixtures: the real data lives in ../shared/data beside the repository, never inside it."""
from __future__ import annotations

from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DATA = (REPO_ROOT / ".." / "shared" / "data").resolve()


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.fail(f"shared data not found at {SHARED_DATA}: tests expect ../shared/data beside the repo")
    return SHARED_DATA


@pytest.fixture(scope="session")
def bad_input_assets(tmp_path_factory):
    """For the bad-input matrix (tests/test_bad_inputs*.py): a random ReLU FeatureNet checkpoint and its x86-cpu
    artefact at 64x64, built once; cases only read them."""
    import torch

    from bad_inputs_support import Assets
    from models.checkpoint import save_checkpoint
    from models.featurenet import FeatureNet, FeatureNetConfig
    from toolkit.cli import main

    root = tmp_path_factory.mktemp("bad-input-assets")
    torch.manual_seed(0)
    checkpoint = save_checkpoint(FeatureNet(FeatureNetConfig(activation="relu")), root / "relu.safetensors")
    artefact = root / "artefact"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "64x64",
                 "-o", str(artefact)]) == 0
    return Assets(root, checkpoint, artefact)


# Test files that take minutes run first, so that with two workers (pytest-xdist, `-n 2` in pyproject.toml) they
# overlap the many short ones instead of finishing alone at the end.
SLOW_FIRST = ("test_readme_tour.py",)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: item.path.name not in SLOW_FIRST)  # stable: every other order is kept
