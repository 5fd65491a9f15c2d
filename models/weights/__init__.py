"""The shipped default weights: ``featurenet-elu`` (the paper's activation) and ``featurenet-relu``
(the deploy variant: ReLU fuses into Conv and quantises), each a safetensors checkpoint with a model card
(``MODEL_CARD-<name>.md``: data, licences, teacher, recipe, budget, metrics, limits) beside it.

They install with the package (package data), so every command's ``--model default`` /
no ``--checkpoint`` works without ``../shared``.
"""
from __future__ import annotations

from pathlib import Path

from models.errors import ModelError

WEIGHTS_DIR = Path(__file__).resolve().parent
SHIPPED = ("featurenet-elu", "featurenet-relu")
DEFAULT = "featurenet-elu"


def shipped_checkpoint(name: str = DEFAULT) -> Path:
    """Path of a shipped checkpoint. Raises ModelError for an unknown name or a missing file."""
    if name not in SHIPPED:
        raise ModelError(f"no shipped model {name!r} (shipped: {', '.join(SHIPPED)})")
    path = WEIGHTS_DIR / f"{name}.safetensors"
    if not path.is_file():
        raise ModelError(f"the shipped weights {path} are missing: reinstall the package")
    return path


def model_card(name: str = DEFAULT) -> Path:
    return WEIGHTS_DIR / f"MODEL_CARD-{name}.md"


ALIASES = {"default": "featurenet-elu", "default-elu": "featurenet-elu", "default-relu": "featurenet-relu",
           "featurenet-elu": "featurenet-elu", "featurenet-relu": "featurenet-relu"}


def resolve_checkpoint(spec: str | Path | None) -> Path:
    """A ``--checkpoint`` value -> a file: None or ``default`` is the shipped ELU model, ``default-relu``
    the ReLU one (``featurenet-elu|relu`` also name them); anything else is a path, returned as given
    unless a file of that alias name exists in the working directory."""
    if spec is None:
        return shipped_checkpoint(DEFAULT)
    text = str(spec)
    if text in ALIASES and not Path(text).exists():
        return shipped_checkpoint(ALIASES[text])
    return Path(spec)
