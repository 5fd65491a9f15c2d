"""The trainer's bfloat16 choice: autocast only where the CPU computes bfloat16 natively."""
from __future__ import annotations

from pathlib import Path

from toolkit.training.cpu_precision import cpu_computes_bf16, cpu_flags

X86 = "processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: fpu sse2 avx2 {extra}\nbogomips\t: 4000\n\nprocessor\t: 1\n"
ARM = "processor\t: 0\nFeatures\t: fp asimd {extra}\nCPU implementer\t: 0x41\n"


def test_the_flags_of_x86_and_arm_cpuinfo_are_read(tmp_path: Path) -> None:
    path = tmp_path / "cpuinfo"
    path.write_text(X86.format(extra="avx512f avx512_bf16"))
    assert {"avx2", "avx512f", "avx512_bf16"} <= cpu_flags(path) and cpu_computes_bf16(path)
    path.write_text(X86.format(extra="avx512f amx_tile amx_bf16"))
    assert cpu_computes_bf16(path)
    # AVX-512 without its bfloat16 extension: oneDNN runs bfloat16 there, but emulated (slower than float32)
    path.write_text(X86.format(extra="avx512f avx512bw avx512vl avx512dq"))
    assert not cpu_computes_bf16(path)
    path.write_text(ARM.format(extra="bf16 sve"))  # Arm's bf16 is not one of the flags oneDNN's x86 kernels use
    assert "bf16" in cpu_flags(path) and not cpu_computes_bf16(path)


def test_no_cpuinfo_means_float32(tmp_path: Path) -> None:
    assert cpu_flags(tmp_path / "missing") == set()
    assert not cpu_computes_bf16(tmp_path / "missing")

