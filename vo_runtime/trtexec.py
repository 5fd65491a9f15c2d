"""Running a TensorRT engine file through NVIDIA's ``trtexec``, for ``verify --engine``.

The engine the artefact README builds (``trtexec --onnx=model.onnx --fp16 --saveEngine=...``) is run by the same
tool that built it: ``--loadEngine`` with the reference input as a raw float32 file (``--loadInputs``), its outputs
written as JSON (``--exportOutput``: a list of ``{"name", "dimensions": "1024x2", "values": [...]}``). So no
TensorRT Python bindings or CUDA memory handling are needed where TensorRT is installed. Not run against a real
TensorRT here (no GPU on the development machines): the tests drive it with a stand-in that writes trtexec's format.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Optional

import numpy as np

from vo_runtime.errors import VORuntimeError
from vo_runtime.references import Outputs, Runner

JETPACK_TRTEXEC = Path("/usr/src/tensorrt/bin/trtexec")  # where JetPack and NVIDIA's containers put it
TRTEXEC_TIMEOUT_S = 600  # loading an engine and one inference take seconds; a hung device should not hang verify


def find_trtexec(given: Optional[str] = None) -> Path:
    """``given``, else ``trtexec`` on PATH, else JetPack's; `VORuntimeError` when there is none."""
    if given:
        path = Path(given)
        if not (path.is_file() and os.access(path, os.X_OK)):
            raise VORuntimeError(f"--trtexec {given}: not an executable file")
        return path
    found = shutil.which("trtexec")
    if found:
        return Path(found)
    if JETPACK_TRTEXEC.is_file():
        return JETPACK_TRTEXEC
    raise VORuntimeError(f"--engine needs TensorRT's trtexec: none on PATH nor at {JETPACK_TRTEXEC} "
                         "(pass --trtexec PATH where TensorRT is installed)")


def parse_exported_outputs(text: str) -> Outputs:
    """trtexec's ``--exportOutput`` JSON as arrays by output name (``dimensions`` "AxB" gives the shape)."""
    try:
        entries = json.loads(text)
        outputs = {}
        for entry in entries:
            shape = [int(side) for side in str(entry["dimensions"]).split("x") if side]
            outputs[str(entry["name"])] = np.asarray(entry["values"]).reshape(shape)
        return outputs
    except (ValueError, KeyError, TypeError) as exc:
        raise VORuntimeError(f"trtexec's exported outputs are not in the expected format ({exc})") from None


def trtexec_runner(engine: Path, trtexec: Path, input_name: str = "image") -> Runner:
    """A `Runner` that runs one input through ``engine`` with ``trtexec`` (one process per input)."""
    if not engine.is_file():
        raise VORuntimeError(f"engine file not found: {engine}")

    def run(tensor: np.ndarray) -> Outputs:
        with tempfile.TemporaryDirectory(prefix="edgefeat-verify-") as folder:
            raw, exported = Path(folder) / "input.bin", Path(folder) / "outputs.json"
            np.ascontiguousarray(tensor, np.float32).tofile(raw)
            command = [str(trtexec), f"--loadEngine={engine}", f"--loadInputs={input_name}:{raw}",
                       f"--exportOutput={exported}", "--iterations=1", "--warmUp=0", "--duration=0", "--avgRuns=1"]
            try:
                result = subprocess.run(command, capture_output=True, text=True, timeout=TRTEXEC_TIMEOUT_S)
            except (OSError, subprocess.TimeoutExpired) as exc:
                raise VORuntimeError(f"trtexec could not run {engine.name}: {exc}") from None
            if result.returncode != 0 or not exported.is_file():
                last = (result.stdout + result.stderr).strip().splitlines()[-1:] or ["no output"]
                raise VORuntimeError(f"trtexec failed on {engine.name} (exit {result.returncode}): {last[0]}")
            return parse_exported_outputs(exported.read_text())

    return run
