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


def test_the_cpu_profile_pads_to_avx512_blocks_and_the_tx2_profile_does_not(tmp_path) -> None:
    assert load_profile("x86-cpu").channel_multiple == 16
    assert load_profile("tx2").channel_multiple == 1  # TensorRT lays out its own tensors
    text = open(load_profile("x86-cpu").source, encoding="utf-8").read()
    bad = tmp_path / "bad.toml"
    bad.write_text(text.replace("channel_multiple = 16", "channel_multiple = 0"))
    with pytest.raises(ProfileError, match="channel_multiple"):
        load_profile(bad)


def test_the_drone_cameras_artefact_carries_its_padding() -> None:
    from vo_runtime.artefact import WIDE_ARTEFACT_DIR, verify_artefact

    padding = verify_artefact(WIDE_ARTEFACT_DIR)["onnx"]["channel_padding"]
    assert padding["multiple"] == 16
    assert [(c["channels"], c["padded"]) for c in padding["chains"]] == [(24, 32)]
    model = onnx.load(str(WIDE_ARTEFACT_DIR / "model.onnx"))
    widths = {t.name: t.dims[0] for t in model.graph.initializer if len(t.dims) == 4}
    producer = next(n for n in model.graph.node if n.name == padding["chains"][0]["producer"])
    assert widths[producer.input[1]] == 32


@pytest.mark.parametrize("target, dense", [("x86-cpu", False), ("x86-cpu", True), ("tx2", False)])
def test_export_pads_the_slim_network_for_the_cpu_only(target: str, dense: bool, tmp_path) -> None:
    # The slim checkpoint's second stage is 24 channels wide with a max-pool after it; the export's parity run
    # (against PyTorch) passes on the padded graph, and the manifest names what was padded.
    import json

    from toolkit.cli import main

    out = tmp_path / f"{target}-{dense}"
    args = ["export", "--target", target, "--checkpoint", "slim-relu", "--input-size", "120x160", "-o", str(out)]
    assert main(args + (["--dense"] if dense else [])) == 0
    padding = json.loads((out / "manifest.json").read_text())["onnx"]["channel_padding"]
    expected = [(24, 32)] if target == "x86-cpu" else []
    assert [(chain["channels"], chain["padded"]) for chain in padding["chains"]] == expected
    model = onnx.load(str(out / "model.onnx"))
    widths = {t.name: t.dims[0] for t in model.graph.initializer if len(t.dims) == 4 and t.dims[1] != 1}
    if target == "x86-cpu":
        producer = next(node for node in model.graph.node if node.name == padding["chains"][0]["producer"])
        assert widths[producer.input[1]] == 32 and 24 not in widths.values()
    else:
        assert 24 in widths.values()
