"""Training only some parts of a model: the rest keeps its weights and its inference behaviour.

`TrainConfig.train_only` names the parts that learn by their module names (``"pixel_head"``, ``"detector"``):
every parameter outside them stops requiring a gradient, and every module outside them stays in eval mode,
so its batch norms use their running statistics, as the exported graph does, and never update them.
Backward then stops at the trained parts (a head-only fine-tune costs little more than a forward pass).
"""
from __future__ import annotations

from torch import nn

from toolkit.errors import ToolkitError


def _inside(name: str, parts: list[str]) -> bool:
    return any(name == part or name.startswith(part + ".") for part in parts)


def _holds(name: str, parts: list[str]) -> bool:
    """Whether the module ``name`` contains one of ``parts`` (the root contains everything)."""
    return name == "" or any(part.startswith(name + ".") for part in parts)


def freeze_outside(model: nn.Module, parts: list[str]) -> list[str]:
    """Stop gradients to every parameter outside ``parts``; return the names of those that still train.

    Raises `ToolkitError` when a part names no module of ``model``. ``parts`` empty: everything trains.
    """
    if not parts:
        return [name for name, _ in model.named_parameters()]
    names = {name for name, _ in model.named_modules()}
    unknown = [part for part in parts if part not in names or part == ""]
    if unknown:
        tops = ", ".join(name for name, _ in model.named_children())
        raise ToolkitError(f"train_only: {unknown[0]!r} is not a part of this model (its parts: {tops})")
    trained = []
    for name, parameter in model.named_parameters():
        keep = _inside(name, parts)
        parameter.requires_grad_(keep)
        if keep:
            trained.append(name)
    return trained


def hold_frozen_in_eval(model: nn.Module, parts: list[str]) -> None:
    """Put every module outside ``parts`` (and not holding one of them) in eval mode, leaving the rest as it is.

    Call it after each ``model.train()``: that call switches every module back to training.
    """
    if not parts:
        return
    for name, module in model.named_modules():
        if not _inside(name, parts) and not _holds(name, parts):
            module.training = False
