"""Whether a CPU trains faster in bfloat16 than in float32.

bfloat16 autocast pays only where the CPU multiplies bfloat16 natively (AVX512_BF16 or AMX): 1.4-1.7x there
(docs/training.md). Elsewhere torch converts every operand and runs float32 kernels: on a 2-core AVX2 AMD EPYC
the tour's 30 steps at batch 4 took 108 s under bfloat16 autocast against 23 s in float32 (4.6x slower).
AVX-512 alone (torch's oneDNN check for bfloat16 kernels) is not enough: without the BF16 extension those kernels
emulate it, 3-4x slower than float32 (onnxruntime's oneDNN notes say the same).
"""
from __future__ import annotations

from pathlib import Path

from vo_runtime.cpu_blocks import cpu_flags

NATIVE_BF16_FLAGS = ("avx512_bf16", "amx_bf16")


def cpu_computes_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """True when the CPU has a native bfloat16 instruction set, so autocast to bfloat16 speeds training up."""
    return any(flag in cpu_flags(cpuinfo) for flag in NATIVE_BF16_FLAGS)
