"""Every artefact the toolkit writes is a valid ONNX graph (issue 31): the full onnx.checker and the target's
op check on each kind, FP16 parity unchanged by the sort, and a graph that fails the checker never written."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import TensorProto, helper

from export.graph_order import sort_topologically
from export.checks import check_against_profile
from export.onnx_export import check_before_writing
from profiles import load_profile
from toolkit.cli import main
from toolkit.compression.report import ort_session
from export.errors import ExportError
from vo_runtime.artefact import verify_artefact

torch.set_num_threads(1)
SIZE = "120x160"  # the smallest size at which the shipped models find enough keypoints for a parity run
PARITY_DIR = Path(__file__).resolve().parents[1] / "export" / "parity_images"


def toolkit(*argv: str) -> None:
    assert main(list(argv)) == 0, argv


@pytest.fixture(scope="module")
def artefacts(shared_data, tmp_path_factory) -> dict[str, Path]:
    """One artefact of every kind the toolkit writes, through the CLI as a user would make them."""
    root = tmp_path_factory.mktemp("kinds")
    out = {name: root / name for name in (
        "x86-fp32", "x86-int8", "x86-fp16", "x86-fp16-export", "x86-dense", "tx2-fp32-elu", "tx2-fp32-relu",
        "tx2-trt-fp16", "tx2-fp16-elu", "tx2-fp16-relu", "pruned-tx2-fp32", "pruned-x86-fp32")}
    export = ("export", "--input-size", SIZE, "--target")
    toolkit(*export, "x86-cpu", "--checkpoint", "default-relu", "-o", str(out["x86-fp32"]))
    toolkit("quantise", "--artefact", str(out["x86-fp32"]), "--mode", "int8", "--calibration-count", "4",
            "-o", str(out["x86-int8"]))
    toolkit("quantise", "--artefact", str(out["x86-fp32"]), "--mode", "fp16", "-o", str(out["x86-fp16"]))
    toolkit(*export, "x86-cpu", "--checkpoint", "default-relu", "--precision", "fp16", "-o", str(out["x86-fp16-export"]))
    toolkit(*export, "x86-cpu", "--checkpoint", "default-relu", "--dense", "-o", str(out["x86-dense"]))
    for model, checkpoint in (("elu", "default"), ("relu", "default-relu")):  # both shipped models
        toolkit(*export, "tx2", "--checkpoint", checkpoint, "--precision", "fp32", "-o", str(out[f"tx2-fp32-{model}"]))
        toolkit("quantise", "--artefact", str(out[f"tx2-fp32-{model}"]), "--mode", "fp16", "-o", str(out[f"tx2-fp16-{model}"]))
    toolkit(*export, "tx2", "-o", str(out["tx2-trt-fp16"]))  # the default: FP32 graph, FP16 as a TensorRT build flag
    pruned = root / "pruned.safetensors"
    toolkit("prune", "--checkpoint", "default-relu", "--ratio", "0.3", "--steps", "0", "--size", SIZE, "--no-eval",
            "--images", str(shared_data / "train_images"), "-o", str(pruned))
    toolkit(*export, "tx2", "--checkpoint", str(pruned), "--precision", "fp32", "-o", str(out["pruned-tx2-fp32"]))
    toolkit(*export, "x86-cpu", "--checkpoint", str(pruned), "-o", str(out["pruned-x86-fp32"]))
    return out


def read(directory: Path) -> tuple[dict, onnx.ModelProto]:
    return verify_artefact(directory), onnx.load(str(directory / "model.onnx"))


@pytest.mark.parametrize("kind", ["x86-fp32", "x86-int8", "x86-fp16", "x86-fp16-export", "x86-dense", "tx2-fp32-elu",
                                  "tx2-fp32-relu", "tx2-trt-fp16", "tx2-fp16-elu", "tx2-fp16-relu", "pruned-tx2-fp32",
                                  "pruned-x86-fp32"])
def test_every_artefact_passes_the_full_checker_and_its_target_op_check(artefacts, kind):
    manifest, model = read(artefacts[kind])
    onnx.checker.check_model(model, full_check=True)  # includes the topological order TensorRT reads in
    assert manifest["onnx"]["checker"] == {"check": "onnx.checker.check_model(full_check=True)", "passed": True,
                                           "onnx_version": onnx.__version__}
    # The tx2 op check applies only where the artefact targets tx2: x86-cpu graphs use DeformConv (opset 19),
    # which TensorRT 8.0 cannot read by design. Each x86 artefact gets its own (x86-cpu) profile's check.
    assert manifest["target"] == ("tx2" if "tx2" in kind else "x86-cpu")
    check_against_profile(model, load_profile(manifest["target"]))
    if manifest["target"] == "tx2":
        assert {node.op_type for node in model.graph.node} <= load_profile("tx2").allowed_ops


def parity_feeds() -> list[dict[str, np.ndarray]]:
    from export.parity import prepare_image

    height, width = (int(v) for v in SIZE.split("x"))
    return [{"image": prepare_image(path, height, width)} for path in sorted(PARITY_DIR.glob("*.png"))]


@pytest.mark.parametrize("model_name", ["elu", "relu"])
def test_fp16_of_both_shipped_models_keeps_todays_parity(artefacts, model_name):
    # The sort reorders nodes and nothing else: the FP16 graph as the float16 converter left it (the unsorted
    # graph every FP16 artefact held before) gives bit-identical outputs, so parity is what it was.
    from onnxruntime.transformers.float16 import convert_float_to_float16

    manifest, sorted_model = read(artefacts[f"tx2-fp16-{model_name}"])
    _, fp32 = read(artefacts[f"tx2-fp32-{model_name}"])
    unsorted = convert_float_to_float16(fp32, keep_io_types=True)
    assert [n.op_type for n in unsorted.graph.node] != [n.op_type for n in sorted_model.graph.node]
    before, after = ort_session(unsorted), ort_session(sorted_model)
    for feed in parity_feeds():
        for old, new in zip(before.run(None, feed), after.run(None, feed)):
            np.testing.assert_array_equal(old, new)
    parity = manifest["quantisation"]["parity_vs_fp32"]
    assert parity["keypoints_unchanged"] >= 0.90 and parity["descriptor_cosine"] > 0.999


def expect_refusal(capsys, argv: list[str], output: Path) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "\n" not in err and "Traceback" not in err, err
    assert "fails onnx.checker" in err and "topologically sorted" in err, err
    assert not output.exists() and not list(output.parent.glob(f".{output.name}*")), "nothing written, no staging left"


def test_an_unsorted_graph_is_refused_with_one_line_and_nothing_written(artefacts, tmp_path, monkeypatch, capsys):
    import export.half

    monkeypatch.setattr(export.half, "topologically_sorted", lambda model: model)  # the float16 converter's order
    expect_refusal(capsys, ["quantise", "--artefact", str(artefacts["tx2-fp32-relu"]), "--mode", "fp16",
                            "-o", str(tmp_path / "fp16")], tmp_path / "fp16")
    expect_refusal(capsys, ["export", "--target", "x86-cpu", "--checkpoint", "default-relu", "--input-size", SIZE,
                            "--precision", "fp16", "-o", str(tmp_path / "export-fp16")], tmp_path / "export-fp16")


def chain_graph(order: list[int]) -> onnx.ModelProto:
    """x -> Relu (a) -> Neg (b) -> Abs (y), nodes stored in ``order``."""
    nodes = [helper.make_node("Relu", ["x"], ["a"], name="relu"), helper.make_node("Neg", ["a"], ["b"], name="neg"),
             helper.make_node("Abs", ["b"], ["y"], name="abs")]
    x, y = (helper.make_tensor_value_info(name, TensorProto.FLOAT, [2]) for name in ("x", "y"))
    graph = helper.make_graph([nodes[i] for i in order], "chain", [x], [y])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])


def test_sort_orders_nodes_keeps_a_sorted_graph_and_refuses_a_cycle():
    unsorted = chain_graph([2, 0, 1])
    with pytest.raises(ExportError, match=r"^the fp16 graph fails onnx\.checker: .*topologically sorted"):
        check_before_writing(unsorted, "the fp16 graph")
    sort_topologically(unsorted.graph)
    assert [n.name for n in unsorted.graph.node] == ["relu", "neg", "abs"]
    assert check_before_writing(unsorted, "the fp16 graph")["passed"] is True
    ordered = chain_graph([0, 1, 2])
    serialised = ordered.SerializeToString()
    sort_topologically(ordered.graph)
    assert ordered.SerializeToString() == serialised  # an already sorted graph is left byte for byte
    cyclic = chain_graph([0, 1, 2])
    cyclic.graph.node[0].input[0] = "b"  # relu reads neg's output, neg reads relu's
    with pytest.raises(ExportError, match="cycle"):
        sort_topologically(cyclic.graph)


def test_manifest_records_the_check_and_the_runtime_stays_onnx_free(artefacts):
    # The runtime trusts the record instead of re-checking: vo_runtime must not import onnx.
    manifest = json.loads((artefacts["tx2-fp16-elu"] / "manifest.json").read_text())
    assert manifest["onnx"]["checker"]["passed"] is True
    import subprocess
    import sys

    probe = ("import sys, vo_runtime; vo_runtime.FeatureExtractor(sys.argv[1]); "
             "assert 'onnx' not in sys.modules and 'torch' not in sys.modules, sorted(sys.modules)")
    result = subprocess.run([sys.executable, "-c", probe, str(artefacts["tx2-fp16-elu"])], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
