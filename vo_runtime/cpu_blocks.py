"""Which of an artefact's graphs suits this CPU (torch-free).

onnxruntime's CPU provider runs convolutions in a blocked layout (NCHWc) on x86: 16 channels a block where the
CPU has AVX-512F, 8 where it has AVX2 only (MLAS's platform setup); on other CPUs nothing is blocked. A max-pool
whose width is not a multiple of the block runs unblocked, with a layout conversion either side, so
`toolkit export --target x86-cpu` writes the graph as traced (``model.onnx``) plus one padded with zero channels
for each wider block (``onnx.block_graphs`` in the manifest; `export.block_graphs`). Every graph gives the same
outputs; only the time differs. The slim network at 480x752: padded to 32 channels it ran 1.3-1.8 ms faster a frame
on an AVX-512 core and 0.8-1.1 ms slower on an AVX2 core, where 24 channels already fill three blocks
(docs/vo_euroc.md, "One graph per channel block").
"""
from __future__ import annotations

import platform
from pathlib import Path
from typing import Any

X86_MACHINES = ("x86_64", "amd64", "i386", "i686", "x86")


def _cpuinfo_field(cpuinfo: Path, keys: tuple[str, ...]) -> str | None:
    """The first processor's value of the first of ``keys`` it lists in ``cpuinfo`` (Linux); None without one."""
    try:
        text = cpuinfo.read_text(errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in keys:
            return value.strip()
    return None


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str]:
    """The first processor's feature flags from ``cpuinfo`` (Linux); empty where there is no such file."""
    return set((_cpuinfo_field(cpuinfo, ("flags", "Features")) or "").split())


def cpu_name(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """The processor's model name from ``cpuinfo`` (Linux), else what `platform` knows."""
    return _cpuinfo_field(cpuinfo, ("model name",)) or platform.processor() or platform.machine()


def nchwc_block(flags: set[str] | None = None, machine: str | None = None) -> int:
    """onnxruntime's channel block on this CPU: 16 with AVX-512F, 8 on other x86 CPUs, 1 (no blocking) elsewhere.

    ``flags`` and ``machine`` default to this machine's (/proc/cpuinfo, `platform.machine`). Linux lists avx512f
    only where the kernel also saves the wide registers, the condition onnxruntime checks too."""
    machine = (platform.machine() if machine is None else machine).lower()
    if machine not in X86_MACHINES:
        return 1
    return 16 if "avx512f" in (cpu_flags() if flags is None else flags) else 8


def graph_file(manifest: dict[str, Any], block: int) -> str:
    """The graph of a verified manifest to run where onnxruntime blocks channels by ``block``: the one padded for
    that block when the artefact has it, else ``onnx.file``."""
    for entry in manifest["onnx"].get("block_graphs", []):
        if entry["block"] == block:
            return entry["file"]
    return manifest["onnx"]["file"]


def graph_for_this_cpu(manifest: dict[str, Any]) -> str:
    """`graph_file` for this machine's block (`nchwc_block`): what `FeatureExtractor` and `verify` load."""
    return graph_file(manifest, nchwc_block())
