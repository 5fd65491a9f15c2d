"""A hand-built keypoint artefact (Harris corners + patch descriptors, no learnt weights) and the
FeatureExtractor contract tested on it.

It honours the artefact contract of `vo_runtime.artefact` (fixed input, K padded rows, ``num_valid``), so the
runtime can be tested end to end before, and independently of, the network export.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from vo_runtime import ArtefactError, FeatureExtractor, VORuntimeError
from vo_runtime.artefact import ARTEFACT_FORMAT, MANIFEST_NAME, MODEL_NAME, sha256_file
from vo_runtime.sequence import list_frames

OPSET = 17


def harris_model(height: int = 240, width: int = 320, max_keypoints: int = 512, border: int = 8,
                 threshold: float = 1e-7) -> onnx.ModelProto:
    grid = np.arange(-6, 7, 2)  # 7x7 samples at stride 2: a 49-D mean-free, unit-norm patch descriptor
    onehot = np.zeros((len(grid) ** 2, 1, 13, 13), np.float32)
    for k, (dy, dx) in enumerate((dy, dx) for dy in grid for dx in grid):
        onehot[k, 0, dy + 6, dx + 6] = 1.0
    sobel = np.array([[-1, 0, 1], [-2, 0, 2], [-1, 0, 1]], np.float32) / 8
    mask = np.zeros((1, 1, height, width), np.float32)
    mask[..., border:-border, border:-border] = 1.0
    inits = {
        "sobel_x": sobel[None, None], "sobel_y": sobel.T.copy()[None, None], "onehot": onehot, "mask": mask,
        "harris_k": np.array(0.04, np.float32), "eps": np.array(1e-6, np.float32),
        "flat_shape": np.array([height * width], np.int64), "k": np.array([max_keypoints], np.int64),
        "desc_shape": np.array([len(onehot), height * width], np.int64), "width": np.array(width, np.int64),
        "threshold": np.array(threshold, np.float32), "axis1": np.array([1], np.int64),
    }
    n = helper.make_node
    nodes = [
        n("AveragePool", ["image"], ["blur"], kernel_shape=[3, 3], pads=[1, 1, 1, 1], count_include_pad=0),
        n("Conv", ["blur", "sobel_x"], ["ix"], pads=[1, 1, 1, 1]),
        n("Conv", ["blur", "sobel_y"], ["iy"], pads=[1, 1, 1, 1]),
        n("Mul", ["ix", "ix"], ["ixx"]), n("Mul", ["iy", "iy"], ["iyy"]), n("Mul", ["ix", "iy"], ["ixy"]),
        *[n("AveragePool", [f"i{c}"], [f"s{c}"], kernel_shape=[5, 5], pads=[2, 2, 2, 2], count_include_pad=0)
          for c in ("xx", "yy", "xy")],
        n("Mul", ["sxx", "syy"], ["d1"]), n("Mul", ["sxy", "sxy"], ["d2"]), n("Sub", ["d1", "d2"], ["det"]),
        n("Add", ["sxx", "syy"], ["tr"]), n("Mul", ["tr", "tr"], ["tr2"]), n("Mul", ["tr2", "harris_k"], ["ktr2"]),
        n("Sub", ["det", "ktr2"], ["resp0"]), n("Mul", ["resp0", "mask"], ["resp"]),
        n("MaxPool", ["resp"], ["local_max"], kernel_shape=[5, 5], pads=[2, 2, 2, 2]),
        n("Equal", ["resp", "local_max"], ["is_max"]), n("Cast", ["is_max"], ["is_max_f"], to=TensorProto.FLOAT),
        n("Mul", ["resp", "is_max_f"], ["nms"]), n("Reshape", ["nms", "flat_shape"], ["flat"]),
        n("TopK", ["flat", "k"], ["scores", "index"], axis=0, largest=1, sorted=1),
        n("Mod", ["index", "width"], ["col"]), n("Div", ["index", "width"], ["row"]),
        n("Cast", ["col"], ["x"], to=TensorProto.FLOAT), n("Cast", ["row"], ["y"], to=TensorProto.FLOAT),
        n("Unsqueeze", ["x", "axis1"], ["x1"]), n("Unsqueeze", ["y", "axis1"], ["y1"]),
        n("Concat", ["x1", "y1"], ["keypoints"], axis=1),
        n("Conv", ["blur", "onehot"], ["patches"], pads=[6, 6, 6, 6]),
        n("Reshape", ["patches", "desc_shape"], ["patch_flat"]),
        n("Gather", ["patch_flat", "index"], ["picked"], axis=1),
        n("Transpose", ["picked"], ["raw"], perm=[1, 0]), n("ReduceMean", ["raw"], ["mean"], axes=[1], keepdims=1),
        n("Sub", ["raw", "mean"], ["centred"]), n("ReduceL2", ["centred"], ["norm"], axes=[1], keepdims=1),
        n("Add", ["norm", "eps"], ["norm_eps"]), n("Div", ["centred", "norm_eps"], ["descriptors"]),
        n("Greater", ["scores", "threshold"], ["valid"]), n("Cast", ["valid"], ["valid_i"], to=TensorProto.INT32),
        n("ReduceSum", ["valid_i"], ["num_valid"], keepdims=1),
    ]
    k, d = max_keypoints, len(onehot)
    graph = helper.make_graph(
        nodes, "harris_patch",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 1, height, width])],
        [helper.make_tensor_value_info("keypoints", TensorProto.FLOAT, [k, 2]),
         helper.make_tensor_value_info("scores", TensorProto.FLOAT, [k]),
         helper.make_tensor_value_info("descriptors", TensorProto.FLOAT, [k, d]),
         helper.make_tensor_value_info("num_valid", TensorProto.INT32, [1])],
        [numpy_helper.from_array(np.asarray(v), name) for name, v in inits.items()],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    onnx.checker.check_model(model, full_check=True)
    return model


def write_artefact(directory: str | Path, height: int = 240, width: int = 320, max_keypoints: int = 512,
                   resize_policy: str = "resize") -> Path:
    """Write ``model.onnx`` and ``manifest.json`` (keypoint mode) into `directory`; return it."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    onnx.save(harris_model(height, width, max_keypoints), directory / MODEL_NAME)
    manifest = {
        "format": ARTEFACT_FORMAT, "mode": "keypoints", "target": "x86", "opset": OPSET, "precision": "fp32",
        "input": {"name": "image", "shape": [1, 1, height, width], "normalisation": {"scale": 1 / 255},
                  "resize_policy": resize_policy},
        "outputs": ["keypoints", "scores", "descriptors", "num_valid"],
        "postprocess": {"max_keypoints": max_keypoints},
        "onnx": {"file": MODEL_NAME, "sha256": sha256_file(directory / MODEL_NAME)},
        "source": {"kind": "test fixture: Harris + patch descriptors"},
    }
    (directory / MANIFEST_NAME).write_text(json.dumps(manifest, indent=2))
    return directory


@pytest.fixture(scope="module")
def artefact(tmp_path_factory):
    return write_artefact(tmp_path_factory.mktemp("harris"))


def test_extractor_maps_keypoints_back_to_the_frame(shared_data, artefact):
    image = cv2.imread(str(list_frames(shared_data / "tum_fr2_desk_snippet" / "rgb")[0]), cv2.IMREAD_GRAYSCALE)
    extractor = FeatureExtractor(artefact)
    full = extractor(image)  # 640x480 -> 320x240 and back
    half = extractor(cv2.resize(image, (320, 240), interpolation=cv2.INTER_AREA))
    assert 50 < len(full) <= 512 and len(full) == len(half)
    np.testing.assert_allclose(full.keypoints, (half.keypoints + 0.5) * 2 - 0.5, atol=1e-4)
    assert np.all(np.diff(full.scores) <= 0)
    np.testing.assert_allclose(np.linalg.norm(full.descriptors, axis=1), 1, atol=1e-4)
    with pytest.raises(VORuntimeError, match="resize policy: reject"):
        FeatureExtractor(artefact, resize_policy="reject")(image)


def test_black_frame_gives_no_keypoints(artefact):
    assert len(FeatureExtractor(artefact)(np.zeros((240, 320), np.uint8))) == 0


def test_corrupt_artefacts_are_refused(artefact, tmp_path):
    copy = write_artefact(tmp_path / "copy")
    with open(copy / "model.onnx", "ab") as handle:
        handle.write(b"\0")
    with pytest.raises(ArtefactError, match="fails its manifest checksum"):
        FeatureExtractor(copy)
    garbage = write_artefact(tmp_path / "garbage")
    (garbage / "model.onnx").write_bytes(b"not a model")
    manifest = json.loads((garbage / "manifest.json").read_text())
    manifest["onnx"]["sha256"] = sha256_file(garbage / "model.onnx")
    (garbage / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ArtefactError, match="onnxruntime cannot load"):
        FeatureExtractor(garbage)
    manifest = json.loads((artefact / "manifest.json").read_text())
    manifest["mode"] = "dense"
    (tmp_path / "dense").mkdir()
    (tmp_path / "dense" / "manifest.json").write_text(json.dumps(manifest))
    (tmp_path / "dense" / "model.onnx").write_bytes((artefact / "model.onnx").read_bytes())
    with pytest.raises(ArtefactError, match="dense artefact"):
        FeatureExtractor(tmp_path / "dense")
    (tmp_path / "nomanifest").mkdir()
    with pytest.raises(ArtefactError, match="manifest.json is missing"):
        FeatureExtractor(tmp_path / "nomanifest")


def test_squeezed_frames_are_measured_and_the_cli_warns(shared_data, artefact, capsys):
    from vo_runtime.cli import main as vo_main

    extractor = FeatureExtractor(artefact)  # 240x320 input
    assert extractor.aspect_distortion(480, 640) == pytest.approx(0.0)
    assert extractor.aspect_distortion(370, 1226) == pytest.approx((1226 / 370) / (320 / 240) - 1.0)
    assert extractor.aspect_distortion(640, 480) == pytest.approx(320 / 240 * 320 / 240 - 1.0)  # portrait
    for sequence, warned in (("kitti_odom06_f000000-000050", True), ("tum_fr2_desk_snippet", False)):
        assert vo_main(["--artefact", str(artefact), "--images", str(shared_data / sequence), "--max-frames", "2",
                        "--no-progress"]) == 0
        err = capsys.readouterr().err
        assert ("--input-size 152x504" in err) is warned and ("warning:" in err) is warned
