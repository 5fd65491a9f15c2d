"""Zero channels for onnxruntime's blocked layout (`export.channel_padding`): same outputs, padded widths, and
only where a max-pool sits between two convolutions."""
from __future__ import annotations

import numpy as np
import onnx
import onnxruntime as ort
import pytest
from onnx import TensorProto, helper, numpy_helper

from export.channel_padding import pad_pooled_channels
from profiles import load_profile
from profiles.errors import ProfileError


def _conv(name: str, source: str, out: int, inputs: int, kernel: int, group: int, rng) -> tuple:
    weight = rng.normal(size=(out, inputs // group, kernel, kernel)).astype(np.float32)
    bias = rng.normal(size=out).astype(np.float32)
    node = helper.make_node("Conv", [source, f"{name}.w", f"{name}.b"], [name], name=name, group=group,
                            pads=[kernel // 2] * 4, kernel_shape=[kernel, kernel])
    return node, [numpy_helper.from_array(weight, f"{name}.w"), numpy_helper.from_array(bias, f"{name}.b")]


def _model(pool: bool = True, extra_output: bool = False, width: int = 24) -> onnx.ModelProto:
    """image [1, 3, 32, 32] -> conv 3->width -> ReLU -> (max-pool) -> depthwise -> ReLU -> conv width->16."""
    rng = np.random.default_rng(0)
    nodes, weights = [], []
    for node, init in (_conv("c1", "image", width, 3, 3, 1, rng),):
        nodes.append(node)
        weights += init
    nodes.append(helper.make_node("Relu", ["c1"], ["r1"]))
    last = "r1"
    if pool:
        nodes.append(helper.make_node("MaxPool", ["r1"], ["p1"], kernel_shape=[2, 2], strides=[2, 2]))
        last = "p1"
    for node, init in (_conv("dw", last, width, width, 3, width, rng),):
        nodes.append(node)
        weights += init
    nodes.append(helper.make_node("Relu", ["dw"], ["r2"]))
    for node, init in (_conv("pw", "r2", 16, width, 1, 1, rng),):
        nodes.append(node)
        weights += init
    side = 16 if pool else 32
    outputs = [helper.make_tensor_value_info("pw", TensorProto.FLOAT, [1, 16, side, side])]
    if extra_output:
        outputs.append(helper.make_tensor_value_info("r1", TensorProto.FLOAT, [1, width, 32, 32]))
    graph = helper.make_graph(nodes, "chain", [helper.make_tensor_value_info("image", TensorProto.FLOAT, [1, 3, 32, 32])],
                              outputs, weights)
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 19)])


def _run(model: onnx.ModelProto, image: np.ndarray) -> list[np.ndarray]:
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    session = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    return session.run(None, {"image": image})


def _weights(model: onnx.ModelProto) -> dict[str, np.ndarray]:
    return {tensor.name: numpy_helper.to_array(tensor) for tensor in model.graph.initializer}


def test_a_pooled_chain_is_padded_to_the_block_with_the_same_outputs() -> None:
    model = _model()
    padded, chains = pad_pooled_channels(model, 16)
    onnx.checker.check_model(padded, full_check=True)
    assert [chain.to_dict() for chain in chains] == [{"producer": "c1", "channels": 24, "padded": 32, "consumer": "pw"}]
    weights = _weights(padded)
    assert weights["c1.w"].shape == (32, 3, 3, 3) and weights["dw.w"].shape == (32, 1, 3, 3)
    assert weights["pw.w"].shape == (16, 32, 1, 1)
    assert not weights["c1.w"][24:].any() and not weights["c1.b"][24:].any() and not weights["pw.w"][:, 24:].any()
    group = [a.i for node in padded.graph.node if node.output[0] == "dw" for a in node.attribute if a.name == "group"]
    assert group == [32]
    image = np.random.default_rng(1).normal(size=(1, 3, 32, 32)).astype(np.float32)
    before, after = _run(model, image), _run(padded, image)
    assert np.array_equal(before[0], after[0])
    assert _weights(model)["c1.w"].shape == (24, 3, 3, 3)  # the input model is left as it was


@pytest.mark.parametrize("case", ["no pool", "tensor read twice", "already a multiple", "multiple 1"])
def test_chains_that_gain_nothing_or_cannot_be_padded_are_left_alone(case: str) -> None:
    model = {"no pool": _model(pool=False), "tensor read twice": _model(extra_output=True),
             "already a multiple": _model(width=32), "multiple 1": _model()}[case]
    padded, chains = pad_pooled_channels(model, 1 if case == "multiple 1" else 16)
    assert chains == []
    assert _weights(padded)["c1.w"].shape == _weights(model)["c1.w"].shape


def test_the_cpu_profile_lists_both_x86_blocks_and_the_tx2_profile_none(tmp_path) -> None:
    assert load_profile("x86-cpu").channel_blocks == (8, 16)
    assert load_profile("tx2").channel_blocks == ()  # TensorRT lays out its own tensors
    text = open(load_profile("x86-cpu").source, encoding="utf-8").read()
    legacy = tmp_path / "legacy.toml"  # a profile of the release before names one block
    legacy.write_text(text.replace("channel_blocks = [8, 16]", "channel_multiple = 16"))
    assert load_profile(legacy).channel_blocks == (16,)
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("channel_blocks = [8, 16]", "channel_blocks = [16, 0]"))
    with pytest.raises(ProfileError, match="channel_blocks"):
        load_profile(bad)


def _conv_widths(model: onnx.ModelProto) -> dict[str, int]:
    return {t.name: t.dims[0] for t in model.graph.initializer if len(t.dims) == 4 and t.dims[1] != 1}


def test_the_drone_cameras_artefact_carries_a_graph_padded_for_avx512() -> None:
    from vo_runtime.artefact import WIDE_ARTEFACT_DIR, verify_artefact

    blocks = verify_artefact(WIDE_ARTEFACT_DIR)["onnx"]["block_graphs"]
    assert [(entry["block"], entry["file"]) for entry in blocks] == [(16, "model.block16.onnx")]
    chain = blocks[0]["chains"][0]
    assert (chain["channels"], chain["padded"]) == (24, 32)
    for name, width in (("model.onnx", 24), ("model.block16.onnx", 32)):
        model = onnx.load(str(WIDE_ARTEFACT_DIR / name))
        producer = next(n for n in model.graph.node if n.name == chain["producer"])
        assert _conv_widths(model)[producer.input[1]] == width


@pytest.mark.parametrize("target, dense", [("x86-cpu", False), ("x86-cpu", True), ("tx2", False)])
def test_export_writes_a_padded_graph_for_the_cpu_only(target: str, dense: bool, tmp_path) -> None:
    # The slim checkpoint's second stage is 24 channels wide with a max-pool after it: a multiple of AVX2's 8-channel
    # blocks, not of AVX-512's 16. The traced graph is model.onnx; the padded one is checked against it and listed.
    import json

    from toolkit.cli import main

    out = tmp_path / f"{target}-{dense}"
    args = ["export", "--target", target, "--checkpoint", "slim-relu", "--input-size", "120x160", "-o", str(out)]
    assert main(args + (["--dense"] if dense else [])) == 0
    blocks = json.loads((out / "manifest.json").read_text())["onnx"]["block_graphs"]
    assert 24 in _conv_widths(onnx.load(str(out / "model.onnx"))).values()
    if target != "x86-cpu":
        assert blocks == [] and not (out / "model.block16.onnx").exists()
        return
    assert [(entry["block"], [(c["channels"], c["padded"]) for c in entry["chains"]]) for entry in blocks] == [
        (16, [(24, 32)])]
    assert blocks[0]["max_abs_diff"] <= 1e-4
    padded = onnx.load(str(out / blocks[0]["file"]))
    assert 24 not in _conv_widths(padded).values()
    image = np.random.default_rng(1).random((1, 1, 120, 160), dtype=np.float32)
    runs = [ort.InferenceSession(str(out / name), providers=["CPUExecutionProvider"]).run(None, {"image": image})
            for name in ("model.onnx", blocks[0]["file"])]
    for traced, block in zip(*runs):
        np.testing.assert_allclose(block, traced, atol=1e-5)
    if not dense:  # quantised, the artefact is one graph: no float graph padded for blocks is carried over
        from vo_runtime.artefact import verify_artefact

        quantised = tmp_path / "fp16"
        assert main(["quantise", "--artefact", str(out), "--mode", "fp16", "-o", str(quantised)]) == 0
        assert verify_artefact(quantised)["onnx"]["block_graphs"] == []
        assert not (quantised / "model.block16.onnx").exists()
