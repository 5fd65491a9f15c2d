"""`toolkit export` for both targets: graph rules, parity, the runtime loading it, and every bad input."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch

from models.weights import shipped_checkpoint
from profiles import load_profile
from toolkit.cli import main
from toolkit.compression.report import ort_session
from vo_runtime import ArtefactError, FeatureExtractor
from vo_runtime.artefact import sha256_file

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    # The shipped ELU weights, copied: random weights give a nearly flat heatmap whose near-ties flip between
    # runtimes (98.5 % identical keypoints), which says nothing about exporting a trained model.
    path = tmp_path_factory.mktemp("ckpt") / "featurenet.safetensors"
    shutil.copyfile(shipped_checkpoint("featurenet-elu"), path)
    return path


@pytest.fixture(scope="module")
def artefacts(checkpoint, tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("artefacts")
    out = {}
    for target in ("tx2", "x86-cpu"):
        assert main(["export", "--target", target, "--checkpoint", str(checkpoint), "-o", str(root / target)]) == 0
        out[target] = root / target
    return out


def read(directory: Path) -> tuple[dict, onnx.ModelProto]:
    return json.loads((directory / "manifest.json").read_text()), onnx.load(str(directory / "model.onnx"))


def test_tx2_graph_is_opset13_with_allowed_ops_only(artefacts):
    manifest, model = read(artefacts["tx2"])
    ops = {node.op_type for node in model.graph.node}
    assert model.opset_import[0].version == 13 and manifest["onnx"]["opset"] == 13
    assert ops <= load_profile("tx2").allowed_ops
    assert not ops & {"DeformConv", "GridSample", "GatherND", "NonZero", "ScatterND"}
    assert "Elu" in ops  # TensorRT fuses it into the conv
    assert manifest["deform_strategy"] == "portable" and manifest["parity"]["min_gather_index"] >= 0
    assert "trtexec --onnx=model.onnx --fp16" in (artefacts["tx2"] / "README.md").read_text()


def test_mass_scoring_exports_for_tx2_with_allowed_ops_and_parity(checkpoint, tmp_path):
    # --score-window 3 (FP16, opset 13): the window sum is an AveragePool, the peak test a 3x3 MaxPool + Equal.
    out = tmp_path / "tx2-mass"
    assert main(["export", "--target", "tx2", "--checkpoint", str(checkpoint), "--score-window", "3", "-o", str(out)]) == 0
    manifest, model = read(out)
    ops = {node.op_type for node in model.graph.node}
    assert "AveragePool" in ops and ops <= load_profile("tx2").allowed_ops
    assert manifest["postprocess"]["score_window"] == 3
    assert manifest["parity"]["keypoints_identical"] >= manifest["parity"]["required_identical"]
    assert main(["export", "--target", "tx2", "--checkpoint", str(checkpoint), "--score-window", "2",
                 "-o", str(tmp_path / "even")]) == 2
    assert not (tmp_path / "even").exists()


def test_x86_graph_uses_native_deformconv(artefacts):
    manifest, model = read(artefacts["x86-cpu"])
    ops = {node.op_type for node in model.graph.node}
    assert "DeformConv" in ops
    assert "Elu" not in ops and {"Exp", "Max"} <= ops  # onnxruntime runs ELU as max(x, exp(min(x, 0)) - 1)
    assert model.opset_import[0].version == 19 and manifest["deform_strategy"] == "native"


@pytest.mark.parametrize("target", ["tx2", "x86-cpu"])
def test_artefact_verifies_and_matches_pytorch(artefacts, checkpoint, target):
    manifest, model = read(artefacts[target])
    assert manifest["onnx"]["sha256"] == sha256_file(artefacts[target] / "model.onnx")
    assert manifest["model"]["checkpoint_sha256"] == sha256_file(checkpoint)
    assert manifest["onnx"]["nodes_after_simplify"] < manifest["onnx"]["nodes_before_simplify"]
    parity = manifest["parity"]
    assert parity["keypoints_identical"] >= 0.99
    assert parity["heatmap_max_abs_diff"] < 1e-4 and parity["descriptors_coarse_max_abs_diff"] < 1e-4
    assert len(parity["images"]) == 4
    shapes = {o.name: [d.dim_value for d in o.type.tensor_type.shape.dim] for o in model.graph.output}
    k = manifest["postprocess"]["max_keypoints"]
    assert shapes == {"keypoints": [k, 2], "scores": [k], "descriptors": [k, 256], "num_valid": [1]}
    dtypes = {o.name: onnx.TensorProto.DataType.Name(o.type.tensor_type.elem_type) for o in model.graph.output}
    onnx_names = {"float32": "FLOAT", "int32": "INT32"}
    assert dtypes == {name: onnx_names[spec["dtype"]] for name, spec in manifest["outputs"].items()}
    if target == "tx2":  # TensorRT 8 has no int64 tensors: every cast in the graph stays 32-bit
        casts = [a.i for n in model.graph.node if n.op_type == "Cast" for a in n.attribute if a.name == "to"]
        assert onnx.TensorProto.INT64 not in casts


def test_runtime_extracts_from_the_artefact_on_a_real_image(artefacts, shared_data):
    image = cv2.imread(str(shared_data / "hpatches_v_dogman" / "v_dogman" / "2.ppm"))
    extract = FeatureExtractor(artefacts["tx2"])
    features = extract(image)
    assert 0 < len(features) <= 1024
    height, width = image.shape[:2]
    assert features.keypoints[:, 0].max() < width and features.keypoints[:, 1].max() < height
    assert np.allclose(np.linalg.norm(features.descriptors, axis=1), 1.0, atol=1e-4)


def test_dense_and_fp16_variants(checkpoint, tmp_path):
    dense = tmp_path / "dense"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "120x160", "--dense", "-o", str(dense)]) == 0
    manifest, model = read(dense)
    assert manifest["mode"] == "dense" and [o.name for o in model.graph.output] == ["heatmap", "descriptors_coarse"]
    with pytest.raises(ArtefactError, match="dense"):
        FeatureExtractor(dense)

    half = tmp_path / "fp16"
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "120x160", "--precision", "fp16", "-o", str(half)]) == 0
    manifest, model = read(half)
    assert manifest["precision_applied"] == "onnx-fp16-weights"
    assert any(init.data_type == onnx.TensorProto.FLOAT16 for init in model.graph.initializer)
    assert manifest["parity"]["keypoints_identical"] >= manifest["parity"]["required_identical"]


def test_profile_check_names_the_offending_op(checkpoint, tmp_path):
    profile_text = (Path(load_profile("tx2").source)).read_text().replace('max_opset = 13', 'max_opset = 19').replace(
        'deform_strategy = "portable"', 'deform_strategy = "native"'
    )
    custom = tmp_path / "tx2-native.toml"
    custom.write_text(profile_text)
    code = main(["export", "--target", str(custom), "--checkpoint", str(checkpoint), "--input-size", "64x64", "-o", str(tmp_path / "x")])
    assert code == 2 and not (tmp_path / "x").exists()
    broken = tmp_path / "broken.toml"
    broken.write_text(profile_text.replace("max_opset = 19\n", ""))
    with pytest.raises(Exception, match="max_opset"):
        load_profile(broken)


def expect_error(capsys, argv: list[str], needle: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err
    assert needle in err, err


def test_bad_inputs_fail_cleanly(checkpoint, artefacts, tmp_path, capsys):
    out = str(tmp_path / "out")
    base = ["export", "--target", "tx2", "--input-size", "64x64"]
    expect_error(capsys, base + ["--checkpoint", str(tmp_path / "nope.safetensors"), "-o", out], "not found")
    corrupt = tmp_path / "corrupt.safetensors"
    corrupt.write_bytes(checkpoint.read_bytes()[:1000])
    expect_error(capsys, base + ["--checkpoint", str(corrupt), "-o", out], "not a readable")
    foreign = tmp_path / "foreign.safetensors"
    from safetensors.torch import save_file

    save_file({"w": torch.zeros(3)}, str(foreign))
    expect_error(capsys, base + ["--checkpoint", str(foreign), "-o", out], "not an EdgeFeat checkpoint")
    expect_error(capsys, ["export", "--target", "jetson-nano", "--checkpoint", str(checkpoint), "-o", out], "unknown target")
    expect_error(capsys, ["export", "--target", "tx2", "--input-size", "60x64", "--checkpoint", str(checkpoint), "-o", out], "divisible by 8")
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    expect_error(capsys, base + ["--checkpoint", str(checkpoint), "-o", str(blocker / "sub")], "is a file, not a directory")
    expect_error(capsys, ["export", "--target", "tx2", "--checkpoint", str(checkpoint), "-o", str(artefacts["tx2"])], "--force")
    assert not (tmp_path / "out").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out.tmp")]


def test_failure_midway_leaves_nothing_and_force_replaces(checkpoint, tmp_path, monkeypatch, capsys):
    target = tmp_path / "art"
    import export.artefact as artefact_module

    def broken_readme(*_args):
        raise OSError("disk full")

    monkeypatch.setattr(artefact_module, "artefact_readme", broken_readme)
    expect_error(capsys, ["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "64x64",
                          "-o", str(target)], "disk full")  # an OSError is one line too, not a traceback
    assert list(tmp_path.iterdir()) == [], "no partial artefact or staging directory"
    monkeypatch.undo()
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "64x64", "-o", str(target)]) == 0
    first = sha256_file(target / "manifest.json")
    assert main(["export", "--target", "x86-cpu", "--checkpoint", str(checkpoint), "--input-size", "64x96", "--force", "-o", str(target)]) == 0
    assert json.loads((target / "manifest.json").read_text())["input"]["shape"] == [1, 1, 64, 96]
    assert sha256_file(target / "manifest.json") != first


def test_console_script_exits_2_without_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "toolkit", "export", "--target", "tx2", "-o", str(tmp_path / "o"), "--checkpoint", str(tmp_path / "none.pth")],
        capture_output=True, text=True,
    )
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"error: checkpoint not found: {tmp_path / 'none.pth'}"]


def test_tampered_artefact_is_rejected_by_the_runtime(artefacts, tmp_path):
    copy = tmp_path / "tampered"
    shutil.copytree(artefacts["x86-cpu"], copy)
    data = bytearray((copy / "model.onnx").read_bytes())
    data[-10] ^= 0xFF
    (copy / "model.onnx").write_bytes(bytes(data))
    with pytest.raises(ArtefactError, match="checksum"):
        FeatureExtractor(copy)


@pytest.mark.parametrize("size", ["240x320", "480x640"])
def test_tx2_graph_survives_every_layer_in_fp16(tmp_path, size):
    # TensorRT built with --fp16 may run any float layer in half precision. Worst case, emulated here:
    # every float tensor of the tx2 graph in FP16 (onnxruntime's converter, nothing kept in FP32). Index
    # arithmetic in float overflowed there (a flat pixel index beyond 65,504) and the gathers read outside
    # their tensors. Shipped weights: random ones give flat heatmaps full of ties.
    from onnxruntime.transformers.float16 import convert_float_to_float16

    out = tmp_path / "tx2"
    assert main(["export", "--target", "tx2", "--input-size", size, "-o", str(out)]) == 0
    _, model = read(out)
    half = convert_float_to_float16(onnx.load(str(out / "model.onnx")), keep_io_types=True, op_block_list=[])
    sessions = [ort_session(m) for m in (model, half)]
    height, width = (int(v) for v in size.split("x"))
    image = cv2.imread(str(Path(__file__).parents[1] / "export" / "parity_images" / "hopper.png"), cv2.IMREAD_GRAYSCALE)
    feed = {"image": (cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA) / 255.0).astype(np.float32)[None, None]}
    (k32, d32, n32), (k16, d16, n16) = (s.run(["keypoints", "descriptors", "num_valid"], feed) for s in sessions)
    k32, d32, k16, d16 = k32[: int(n32[0])], d32[: int(n32[0])], k16[: int(n16[0])], d16[: int(n16[0])]
    assert len(k32) > 200 and abs(len(k16) - len(k32)) <= 0.02 * len(k32)
    distance = np.linalg.norm(k32[:, None] - k16[None], axis=2)
    nearest = distance.argmin(axis=1)
    found = distance[np.arange(len(k32)), nearest] < 0.5
    assert found.mean() >= 0.97
    assert np.median(np.sum(d32[found] * d16[nearest[found]], axis=1)) >= 0.99

