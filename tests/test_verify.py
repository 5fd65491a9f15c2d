"""`python -m vo_runtime verify` / `toolkit verify`: an artefact's reference inputs run again and compared with the
outputs of its parity run; passes on a fresh export, fails in one clear line on a tampered one."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from toolkit.cli import main as toolkit_main
from vo_runtime.artefact import DEFAULT_ARTEFACT_DIR, WIDE_ARTEFACT_DIR, sha256_file
from vo_runtime.references import REFERENCE_NAME
from vo_runtime.verify import main as verify_main
from vo_runtime.version import __version__

SIZE = "120x160"  # small: the checks are about the comparison, not the network


@pytest.fixture(scope="module")
def exported(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("verify") / "cpu"
    assert toolkit_main(["export", "--target", "x86-cpu", "--checkpoint", "default-relu", "--input-size", SIZE,
                         "-o", str(out)]) == 0
    return out


def _copy(artefact: Path, tmp_path: Path) -> Path:
    copy = tmp_path / "copy"
    shutil.copytree(artefact, copy)
    return copy


def _rewrite_references(artefact: Path, change) -> None:
    """Change the stored outputs and record the new file's checksum, as a tamperer who knows the format would."""
    path = artefact / REFERENCE_NAME
    with np.load(path) as data:
        arrays = {key: data[key] for key in data.files}
    change(arrays)
    with open(path, "wb") as handle:
        np.savez_compressed(handle, **arrays)
    manifest = json.loads((artefact / "manifest.json").read_text())
    manifest["reference"]["sha256"] = sha256_file(path)
    (artefact / "manifest.json").write_text(json.dumps(manifest))


def _one_error_line(capsys) -> str:
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), captured.err
    return lines[0]


def test_a_fresh_export_ships_references_and_passes_on_the_cpu(exported: Path) -> None:
    manifest = json.loads((exported / "manifest.json").read_text())
    assert manifest["toolkit_version"] == __version__
    assert manifest["reference"]["images"] == ["hopper-dark.png", "hopper.png"]
    assert (exported / REFERENCE_NAME).stat().st_size < 200_000
    assert "python -m vo_runtime verify" in (exported / "README.md").read_text()
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    result = subprocess.run([sys.executable, "-m", "vo_runtime", "verify", str(exported), "--providers", "cpu", "--json"],
                            capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["passed"] and summary["runs_on"] == "cpu" and summary["written_by"] == __version__
    assert summary["keypoint_agreement"] >= 0.99 and summary["descriptor_distance_mean"] < 0.01
    assert summary["reference_keypoints"] >= 100


def test_toolkit_verify_is_the_same_command(exported: Path, capsys) -> None:
    assert toolkit_main(["verify", str(exported)]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("passed on cpu")


def test_a_reference_file_changed_after_export_fails_its_checksum(exported: Path, tmp_path: Path, capsys) -> None:
    artefact = _copy(exported, tmp_path)
    with open(artefact / REFERENCE_NAME, "r+b") as handle:
        handle.seek(200)
        byte = handle.read(1)
        handle.seek(200)
        handle.write(bytes([byte[0] ^ 0xFF]))
    assert verify_main([str(artefact)]) == 2
    assert "reference.npz fails its manifest checksum" in _one_error_line(capsys)


def test_moved_reference_keypoints_fail_in_one_line(exported: Path, tmp_path: Path, capsys) -> None:
    artefact = _copy(exported, tmp_path)

    def shift(arrays: dict) -> None:
        for key in [k for k in arrays if k.endswith(".keypoints")]:
            arrays[key] = arrays[key] + 3.0

    _rewrite_references(artefact, shift)
    assert verify_main([str(artefact), "--providers", "cpu"]) == 2
    line = _one_error_line(capsys)
    assert line.startswith("error: verify failed on cpu: only ") and "reference keypoints found within 1 px" in line


def test_changed_reference_descriptors_fail_in_one_line(exported: Path, tmp_path: Path, capsys) -> None:
    artefact = _copy(exported, tmp_path)

    def halve(arrays: dict) -> None:  # unit vectors at half length: each lies 0.5 from the true one
        for key in [k for k in arrays if k.endswith(".descriptors")]:
            arrays[key] = arrays[key] / 2

    _rewrite_references(artefact, halve)
    assert verify_main([str(artefact)]) == 2
    assert "mean descriptor distance 0.500 (at most 0.1 allowed)" in _one_error_line(capsys)
    # a looser tolerance is the user's call
    assert verify_main([str(artefact), "--max-descriptor-distance", "0.6"]) == 0


def test_an_artefact_without_references_says_how_to_get_them(exported: Path, tmp_path: Path, capsys) -> None:
    artefact = _copy(exported, tmp_path)
    manifest = json.loads((artefact / "manifest.json").read_text())
    del manifest["reference"]
    (artefact / "manifest.json").write_text(json.dumps(manifest))
    assert verify_main([str(artefact)]) == 2
    assert "ships no reference outputs" in _one_error_line(capsys)


@pytest.mark.parametrize("argv, message", [
    (["--min-keypoint-agreement", "1.5"], "--min-keypoint-agreement is a share in [0, 1]"),
    (["--providers", "tensorrt"], "execution provider tensorrt is not available"),
    (["--trtexec", "/bin/true"], "--trtexec runs an --engine file"),
    (["--engine", "missing.plan", "--trtexec", "/bin/true"], "engine file not found"),
])
def test_bad_options_are_one_line(exported: Path, capsys, argv: list[str], message: str) -> None:
    assert verify_main([str(exported), *argv]) == 2
    assert message in _one_error_line(capsys)


FAKE_TRTEXEC = """\
#!{python}
# Stands in for trtexec --loadEngine: runs the "engine" (here the artefact's ONNX file) in onnxruntime and writes
# --exportOutput in trtexec's JSON layout.
import json, sys
import numpy as np, onnxruntime as ort
args = dict(a.lstrip("-").split("=", 1) for a in sys.argv[1:] if "=" in a)
if {fail}:
    print("[E] [TRT] engine deserialisation failed"); sys.exit(1)
session = ort.InferenceSession(args["loadEngine"], providers=["CPUExecutionProvider"])
name, raw = args["loadInputs"].split(":", 1)
tensor = np.fromfile(raw, np.float32).reshape(session.get_inputs()[0].shape)
values = session.run(None, {{name: tensor}})
entries = [{{"name": o.name, "dimensions": "x".join(map(str, v.shape)), "values": v.reshape(-1).tolist()}}
           for o, v in zip(session.get_outputs(), values)]
open(args["exportOutput"], "w").write(json.dumps(entries))
"""


def _fake_trtexec(tmp_path: Path, fail: bool) -> Path:
    script = tmp_path / "trtexec"
    script.write_text(textwrap.dedent(FAKE_TRTEXEC.format(python=sys.executable, fail=fail)))
    script.chmod(0o755)
    return script


def test_an_engine_file_runs_through_trtexec(exported: Path, tmp_path: Path, capsys) -> None:
    engine = exported / "model.onnx"  # what the stand-in "deserialises"
    assert verify_main([str(exported), "--engine", str(engine), "--trtexec", str(_fake_trtexec(tmp_path, False))]) == 0
    assert "passed on engine model.onnx" in capsys.readouterr().out
    assert verify_main([str(exported), "--engine", str(engine), "--trtexec", str(_fake_trtexec(tmp_path, True))]) == 2
    assert "trtexec failed on model.onnx (exit 1): [E] [TRT] engine deserialisation failed" in _one_error_line(capsys)


def test_a_dense_artefact_is_judged_by_its_heads(tmp_path: Path, capsys) -> None:
    out = tmp_path / "dense"
    assert toolkit_main(["export", "--target", "x86-cpu", "--checkpoint", "default-relu", "--input-size", SIZE,
                         "--dense", "-o", str(out)]) == 0
    capsys.readouterr()
    assert verify_main([str(out), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["heatmap_max_diff"] < 1e-3 and summary["descriptor_distance_mean"] < 0.01


@pytest.mark.parametrize("artefact", [DEFAULT_ARTEFACT_DIR, WIDE_ARTEFACT_DIR], ids=["default", "wide"])
def test_the_shipped_artefacts_pass_verify(artefact: Path, capsys) -> None:
    # Artefacts exported before 0.2.0 get their references with `python -m export.reference DIR`.
    assert verify_main([str(artefact), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["keypoint_agreement"] >= 0.99


def test_an_older_artefact_gets_references_without_its_model_changing(exported: Path, tmp_path: Path) -> None:
    from export.reference import add_references
    from vo_runtime.output_listing import foreign_entries, read_listing, write_listing

    artefact = _copy(exported, tmp_path)
    manifest = json.loads((artefact / "manifest.json").read_text())
    del manifest["reference"]  # as written before 0.2.0
    (artefact / "manifest.json").write_text(json.dumps(manifest))
    (artefact / REFERENCE_NAME).unlink()
    write_listing(artefact, read_listing(exported)["kind"])
    model = sha256_file(artefact / "model.onnx")
    add_references(artefact)
    assert sha256_file(artefact / "model.onnx") == model
    assert verify_main([str(artefact)]) == 0
    assert foreign_entries(artefact, read_listing(artefact)) == []  # still export's own output for --force
