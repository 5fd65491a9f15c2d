"""`toolkit quantise`: INT8 (QDQ, per-channel, calibrated on real images) and FP16 artefacts that run in
onnxruntime, their manifests, the per-layer sensitivity pass, and the bad inputs."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto

from export.artefact import ExportOptions, export_artefact
from models.checkpoint import save_checkpoint
from models.featurenet import FeatureNetConfig
from toolkit.cli import main
from toolkit.compression.images import load_images
from toolkit.compression.proxy import calibrated_random_featurenet
from toolkit.compression.sensitivity import conv_nodes, head_output_convs, layer_sensitivity
from vo_runtime import FeatureExtractor
from vo_runtime.artefact import verify_artefact

torch.set_num_threads(1)
SIZE = (64, 96)
SMALL = FeatureNetConfig(widths=[16, 24, 32, 64], blocks=[0, 1, 1, 2], head_channels=64, descriptor_dim=64,
                         activation="relu")


@pytest.fixture(scope="module")
def artefacts(shared_data, tmp_path_factory) -> dict[str, Path]:
    # Random weights with image-calibrated BatchNorm (ReLU deploy variant): exercises the path, claims nothing.
    root = tmp_path_factory.mktemp("quant")
    images = load_images(shared_data / "train_images", 8, SIZE)[0]
    checkpoint = save_checkpoint(calibrated_random_featurenet(SMALL, images), root / "relu.safetensors")
    out = {}
    for target in ("x86-cpu", "tx2"):
        out[target] = export_artefact(ExportOptions(target=target, output=root / target, checkpoint=checkpoint,
                                                    input_size=SIZE, precision="fp32"), log=lambda _m: None)
    return out


def read(directory: Path) -> tuple[dict, onnx.ModelProto]:
    return json.loads((directory / "manifest.json").read_text()), onnx.load(str(directory / "model.onnx"))


def producers(model: onnx.ModelProto) -> dict[str, onnx.NodeProto]:
    return {out: node for node in model.graph.node for out in node.output}


def run_on_real_image(directory: Path, shared_data: Path):
    gray = cv2.imread(str(shared_data / "hpatches_v_dogman" / "v_dogman" / "1.ppm"), cv2.IMREAD_GRAYSCALE)
    return FeatureExtractor(directory, threads=1)(gray)


def test_int8_artefact_is_qdq_calibrated_and_runs(artefacts, shared_data, tmp_path, capsys):
    out = tmp_path / "int8"
    calibration = shared_data / "train_images" / "bsds500"
    argv = ["quantise", "--artefact", str(artefacts["x86-cpu"]), "--mode", "int8", "--calibration", str(calibration),
            "--calibration-count", "4", "--keep-sensitive", "2", "-o", str(out)]
    assert main(argv) == 0
    assert "sensitivity" in capsys.readouterr().out
    manifest, model = read(out)
    assert verify_artefact(out)["onnx"]["sha256"] == manifest["onnx"]["sha256"]
    q = manifest["quantisation"]
    assert manifest["precision"] == "int8" and manifest["precision_applied"] == "onnx-int8-qdq"
    assert q["calibration"]["count"] == 4 and q["calibration"]["folder"] == str(calibration)
    assert len(q["calibration"]["images"]) == 4
    assert manifest["source_artefact"]["onnx_sha256"] == read(artefacts["x86-cpu"])[0]["onnx"]["sha256"]
    # Sensitivity: one entry per conv with learned weights, worst first; the two worst others stayed float.
    _, fp32 = read(artefacts["x86-cpu"])
    errors = [item["relative_error"] for item in q["sensitivity"]]
    assert len(errors) == len(conv_nodes(fp32)) and errors == sorted(errors, reverse=True)
    floats = q["float_nodes"]
    heads, kept = floats["head_outputs"], floats["sensitive"]
    assert len(heads) == 2 and all(n.endswith(("detector.1/Conv", "layers.6/Conv")) for n in heads)  # the logits
    assert len(floats["fixed_kernels"]) == 2 and all("/cell_contrast/" in n for n in floats["fixed_kernels"])
    assert len(floats["single_channel"]) == 1 and "stem" in floats["single_channel"][0]  # 1 -> 16 channels
    always_float = heads + floats["fixed_kernels"] + floats["single_channel"]
    assert len(kept) == 2 and not set(kept) & set(always_float)
    assert kept == [item["node"] for item in q["sensitivity"] if item["node"] not in always_float][:2]
    made_by = producers(model)
    convs = {node.name: node for node in model.graph.node if node.op_type in ("Conv", "Gemm")}
    assert sum(node.op_type == "Gemm" for node in convs.values()) == 1  # the descriptor projection, quantised
    for name, node in convs.items():
        weight_is_dequantised = node.input[1] in made_by and made_by[node.input[1]].op_type == "DequantizeLinear"
        assert weight_is_dequantised == (name not in always_float + kept), name
    assert sum(node.op_type == "QuantizeLinear" for node in model.graph.node) > 0
    parity = q["parity_vs_fp32"]
    assert 0.0 < parity["keypoints_unchanged"] <= 1.0 and parity["descriptor_cosine"] > 0.9
    assert q["latency_ms_1thread"]["fp32"] > 0 and q["latency_ms_1thread"]["int8"] > 0
    features = run_on_real_image(out, shared_data)
    reference = run_on_real_image(artefacts["x86-cpu"], shared_data)
    assert len(features.keypoints) > 0 and features.descriptors.dtype == np.float32
    shared = {tuple(p) for p in np.round(features.keypoints).astype(int)} & {tuple(p) for p in np.round(reference.keypoints).astype(int)}
    assert len(shared) > len(reference.keypoints) // 2  # INT8 moves some keypoints, not most


@pytest.mark.parametrize("target", ["x86-cpu", "tx2"])
def test_fp16_artefact_keeps_fp32_io_and_runs(artefacts, shared_data, tmp_path, target):
    out = tmp_path / f"fp16-{target}"
    assert main(["quantise", "--artefact", str(artefacts[target]), "--mode", "fp16", "-o", str(out)]) == 0
    manifest, model = read(out)
    verify_artefact(out)
    assert manifest["precision"] == "fp16" and manifest["target"] == target
    assert "calibration" not in manifest["quantisation"]
    float_weights = [init for init in model.graph.initializer if init.data_type in (TensorProto.FLOAT, TensorProto.FLOAT16)]
    assert all(init.data_type == TensorProto.FLOAT16 for init in float_weights if len(init.dims) == 4)
    assert model.graph.input[0].type.tensor_type.elem_type == TensorProto.FLOAT
    for output in model.graph.output:
        assert output.type.tensor_type.elem_type in (TensorProto.FLOAT, TensorProto.INT32)
    assert manifest["quantisation"]["parity_vs_fp32"]["descriptor_cosine"] > 0.99
    features = run_on_real_image(out, shared_data)
    assert features.descriptors.dtype == np.float32 and len(features.keypoints) > 0


def test_sensitivity_ranks_a_coarse_layer_first(artefacts, shared_data):
    # Degrade one conv's weights so that int8 rounding of them costs far more than anywhere else.
    _, model = read(artefacts["x86-cpu"])
    inits = {init.name: init for init in model.graph.initializer}
    victim = next(n for n in model.graph.node if n.op_type == "Conv" and "pointwise" in n.name)
    weight = onnx.numpy_helper.to_array(inits[victim.input[1]]).copy()
    weight[:, :1] = 1000.0 * np.abs(weight).max()  # one huge input column per channel: small weights underflow
    inits[victim.input[1]].CopyFrom(onnx.numpy_helper.from_array(weight, victim.input[1]))
    images = load_images(shared_data / "train_images", 2, SIZE)[0]
    # The cell-pixel head's first conv reads per-cell contrast-normalised pixels and is itself among the most
    # INT8-sensitive layers of a random net; the degraded layer must outrank every other layer.
    ranking = [item for item in layer_sensitivity(model, images) if "pixel_head" not in item.node]
    assert ranking[0].node == victim.name and ranking[0].kind == "pointwise"
    assert set(head_output_convs(model)) == {n.name for n in model.graph.node if n.op_type == "Conv"
                                             and ("detector.1" in n.name or "descriptor.1" in n.name
                                                  or "pixel_head/layers/layers.6" in n.name)}


def expect_error(capsys, argv: list[str], needle: str) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err
    assert needle in err, err


def test_bad_inputs_exit_2_with_one_line(artefacts, tmp_path, capsys):
    out = tmp_path / "out"
    expect_error(capsys, ["quantise", "--artefact", str(artefacts["tx2"]), "--mode", "int8", "-o", str(out)], "no fast INT8")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("not an image")
    expect_error(capsys, ["quantise", "--artefact", str(artefacts["x86-cpu"]), "--mode", "int8", "--calibration", str(empty),
                          "-o", str(out)], "no images")
    tampered = tmp_path / "tampered"
    tampered.mkdir()
    for item in artefacts["x86-cpu"].iterdir():
        (tampered / item.name).write_bytes(item.read_bytes())
    with open(tampered / "model.onnx", "ab") as handle:
        handle.write(b"\0")
    expect_error(capsys, ["quantise", "--artefact", str(tampered), "--mode", "fp16", "-o", str(out)], "checksum")
    expect_error(capsys, ["quantise", "--artefact", str(artefacts["x86-cpu"]), "--mode", "fp16",
                          "-o", str(artefacts["x86-cpu"])], "its own directory")
    assert not out.exists()
