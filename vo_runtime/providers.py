"""Which onnxruntime execution providers run the artefact: the best available, or exactly those asked for.

On a Jetson the network belongs on the GPU: TensorRT (FP16, engines cached on disk, since building one
takes minutes) first, then CUDA, then the CPU. onnxruntime places every node on the first provider in the
list that can run it, so a chain also covers ops TensorRT lacks (e.g. DeformConv in an x86 artefact).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Sequence

from vo_runtime.errors import ArtefactError, VORuntimeError, first_line

# Short names a user types, in the order "auto" prefers them.
PROVIDER_NAMES = {
    "tensorrt": "TensorrtExecutionProvider",
    "cuda": "CUDAExecutionProvider",
    "cpu": "CPUExecutionProvider",
}
AUTO = "auto"


def engine_cache_dir() -> Path:
    """Where TensorRT engines are cached: $EDGEFEAT_CACHE, else $XDG_CACHE_HOME/edgefeat, else ~/.cache/edgefeat."""
    root = os.environ.get("EDGEFEAT_CACHE")
    if root:
        return Path(root) / "tensorrt"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "edgefeat" / "tensorrt"


def parse_providers(text: str | Sequence[str] | None) -> list[str]:
    """``"auto"``, ``"cuda,cpu"`` or ``["tensorrt", "cpu"]`` -> short names; raise `VORuntimeError` on others."""
    if text is None:
        return [AUTO]
    names = [n.strip().lower() for n in (text.split(",") if isinstance(text, str) else text)]
    names = [n for n in names if n]
    if not names:
        raise VORuntimeError("no execution provider given (auto, or a list of: tensorrt, cuda, cpu)")
    if AUTO in names:
        if len(names) > 1:
            raise VORuntimeError("execution provider 'auto' cannot be combined with others")
        return [AUTO]
    for name in names:
        if name not in PROVIDER_NAMES:
            raise VORuntimeError(f"unknown execution provider {name!r} (auto, or a list of: {', '.join(PROVIDER_NAMES)})")
    if len(set(names)) != len(names):
        raise VORuntimeError(f"execution provider listed twice: {','.join(names)}")
    return names


def choose_providers(requested: Sequence[str], available: Sequence[str],
                     cache_dir: Path | None = None) -> list[tuple[str, dict[str, Any]]]:
    """The (provider, options) list for an onnxruntime session.

    Args:
        requested: short names from `parse_providers`; ``["auto"]`` takes every available one in preference order.
        available: ``onnxruntime.get_available_providers()``.
        cache_dir: TensorRT engine cache (default `engine_cache_dir`).
    Raises:
        VORuntimeError: a requested provider this onnxruntime build does not have (one line naming what it has).
    """
    if list(requested) == [AUTO]:
        names = [n for n, full in PROVIDER_NAMES.items() if full in available] or ["cpu"]
    else:
        missing = [n for n in requested if PROVIDER_NAMES[n] not in available]
        if missing:
            have = ", ".join(n for n, full in PROVIDER_NAMES.items() if full in available) or "none"
            raise VORuntimeError(f"execution provider {missing[0]} is not available in this onnxruntime "
                                 f"(it has: {have}; tensorrt and cuda need an onnxruntime-gpu build)")
        names = list(requested)
    chain = []
    for name in names:
        options: dict[str, Any] = {}
        if name == "tensorrt":
            folder = cache_dir or engine_cache_dir()
            options = {"trt_fp16_enable": True, "trt_engine_cache_enable": True, "trt_engine_cache_path": str(folder),
                       "trt_timing_cache_enable": True, "trt_timing_cache_path": str(folder)}
        chain.append((PROVIDER_NAMES[name], options))
    return chain


def short_name(provider: str) -> str:
    """``"CUDAExecutionProvider"`` -> ``"cuda"`` (unknown names pass through)."""
    for name, full in PROVIDER_NAMES.items():
        if full == provider:
            return name
    return provider


def open_session(model_path: str | Path, threads: int = 1, providers: str | Sequence[str] | None = "auto") -> Any:
    """An onnxruntime session on ``model_path`` with the providers asked for (`parse_providers`), TensorRT's engine
    cache folder made first. ``short_name`` of ``session.get_providers()`` says what it really runs on.

    Raises:
        VORuntimeError: a bad or missing provider, or a model onnxruntime cannot load (one line).
    """
    import onnxruntime as ort

    chain = choose_providers(parse_providers(providers), ort.get_available_providers())
    for _, settings in chain:
        if "trt_engine_cache_path" in settings:  # TensorRT writes engines there; it must exist first
            Path(settings["trt_engine_cache_path"]).mkdir(parents=True, exist_ok=True)
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    try:
        return ort.InferenceSession(str(model_path), options, providers=[name for name, _ in chain],
                                    provider_options=[settings for _, settings in chain])
    except Exception as exc:  # onnxruntime raises several unrelated types for a bad model
        raise ArtefactError(f"onnxruntime cannot load {Path(model_path).parent}: {first_line(exc)}") from None
