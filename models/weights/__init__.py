"""The shipped weights: the defaults ``featurenet-elu`` (the paper's activation) and ``featurenet-relu`` (the
deploy variant: ReLU fuses into Conv and quantises), and ``featurenet-slim-relu`` (a faster student of the ReLU
one for large inputs, opt-in), each a safetensors checkpoint with a model card
(``MODEL_CARD-<name>.md``: data, licences, teacher, recipe, budget, metrics, limits) beside it.

They install with the package (package data), so every command's ``--model default`` /
no ``--checkpoint`` works without ``../shared``.
"""
from __future__ import annotations

from pathlib import Path

from models.errors import ModelError

WEIGHTS_DIR = Path(__file__).resolve().parent
# featurenet-slim-relu: featurenet-relu with a stride-2 stem and a quarter of its channels cut, distilled from it
# (toolkit/compression/slim.py): 0.7 of its time at the drone camera's 480x752, not a default (docs/compression.md)
SHIPPED = ("featurenet-elu", "featurenet-relu", "featurenet-slim-relu")
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
           "featurenet-elu": "featurenet-elu", "featurenet-relu": "featurenet-relu",
           "slim-relu": "featurenet-slim-relu", "featurenet-slim-relu": "featurenet-slim-relu"}


def resolve_checkpoint(spec: str | Path | None) -> Path:
    """A ``--checkpoint`` value -> a file: None or ``default`` is the shipped ELU model, ``default-relu``
    the ReLU one, ``slim-relu`` the slim ReLU one (``featurenet-elu|relu|slim-relu`` also name them); anything
    else is a path, returned as given unless a file of that alias name exists in the working directory."""
    if spec is None:
        return shipped_checkpoint(DEFAULT)
    text = str(spec)
    if text in ALIASES and not Path(text).exists():
        return shipped_checkpoint(ALIASES[text])
    return Path(spec)
