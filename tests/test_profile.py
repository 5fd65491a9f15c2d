"""`toolkit profile`: counts (fvcore vs ONNX graph), roofline, calibration fit, CLI outputs and bad input."""
from __future__ import annotations

import json
import random
from pathlib import Path

import pytest
import torch
from torch import nn

from export.artefact import ExportOptions, export_artefact
from export.graphs import KEYPOINT_OUTPUTS, KeypointGraph
from export.onnx_export import export_onnx, trace_to_onnx
from models.checkpoint import save_checkpoint
from models.deform import set_deform_strategy
from models.featurenet import FeatureNet
from models.superpoint import SuperPointNet
from profiles import load_profile
from toolkit.cli import main
from toolkit.profiling.calibration import FitResult, fit_factors
from toolkit.profiling.counts import KINDS, LayerCost, deform_macs, fvcore_count, onnx_layer_costs
from toolkit.profiling.roofline import design_row, hardware_model, predict_layers

torch.set_num_threads(1)
SIZE = (64, 96)


def _keypoint_graph(net: nn.Module, opset: int, strategy: str):
    height, width = SIZE
    set_deform_strategy(net, "native")
    module = KeypointGraph(net.eval(), height, width, 100, 4, 0.005, 4).eval()
    fvcore_total, modules = fvcore_count(module, torch.zeros(1, 1, height, width))
    set_deform_strategy(net, strategy)
    exported = export_onnx(module, torch.zeros(1, 1, height, width), opset, KEYPOINT_OUTPUTS).model
    return fvcore_total, modules, onnx_layer_costs(exported)


@pytest.mark.parametrize("make_net", [FeatureNet, SuperPointNet], ids=["featurenet", "superpoint"])
def test_fvcore_and_onnx_counts_agree_within_one_percent(make_net):
    torch.manual_seed(0)
    fvcore_total, modules, layers = _keypoint_graph(make_net(), 19, "native")
    onnx_total = sum(layer.macs for layer in layers)
    assert abs(onnx_total / fvcore_total - 1.0) < 0.01
    # The network's convs, counted by hand from the shapes seen in a forward pass, are a lower bound.
    assert fvcore_total > _hand_conv_macs(make_net(), *SIZE)


def _hand_conv_macs(net: nn.Module, height: int, width: int) -> int:
    total = 0

    def count(module: nn.Conv2d, inputs, output) -> None:
        nonlocal total
        kh, kw = module.kernel_size
        total += module.out_channels * (module.in_channels // module.groups) * kh * kw * output.shape[2] * output.shape[3]

    hooks = [m.register_forward_hook(count) for m in net.modules() if isinstance(m, nn.Conv2d)]
    with torch.no_grad():
        net.eval()(torch.zeros(1, 1, height, width))
    for hook in hooks:
        hook.remove()
    return total


def test_deformable_conv_is_counted_by_its_handler():
    torch.manual_seed(0)
    net = FeatureNet()
    _, modules, layers = _keypoint_graph(net, 19, "native")
    locations = (SIZE[0] // 8) * (SIZE[1] // 8)
    expected = deform_macs(128, 128, locations, modulated=True)
    deform_row = next(m for m in modules if m.name == "net.deform")
    # The module's own ops: the deformable op (fvcore alone counts it as 0), the offset branch's ReLU
    # (128 channels) and the mask's sigmoid (9 taps), one MAC per element each.
    assert deform_row.macs == expected + 128 * locations + 9 * locations
    assert [l.macs for l in layers if l.op_type == "DeformConv"] == [expected]


def test_hand_counted_small_graph():
    # conv 1->4 3x3 on 8x8 (2304 MACs), ELU (256), 2x2 max-pool (16 outputs x 4 ch x 4 = 256): 2816.
    module = nn.Sequential(nn.Conv2d(1, 4, 3, padding=1), nn.ELU(), nn.MaxPool2d(2, 2)).eval()
    image = torch.rand(1, 1, 8, 8)
    total, _ = fvcore_count(module, image)
    layers = onnx_layer_costs(trace_to_onnx(module, image, 17, ("out",)))
    assert total == 2816
    assert sum(l.macs for l in layers) == 2816
    assert [l.kind for l in layers] == ["conv", "activation", "pool"]
    conv = layers[0]
    assert (conv.input_elements, conv.output_elements, conv.weight_elements) == (64, 256, 40)


def _layer(macs: int, elements: int, op: str = "Conv", kind: str = "conv", producer: str = "", consumers: int = 1) -> LayerCost:
    return LayerCost("l", op, kind, macs, elements, elements, 0, [], producer, consumers)


def test_roofline_bound_fusion_and_formula():
    hardware = hardware_model(load_profile("tx2"), "fp32", "maxn")
    compute_heavy = _layer(10**9, 1000)
    memory_heavy = _layer(1000, 10**7, "Add", "elementwise")
    fused = _layer(1000, 10**7, "Relu", "elementwise", producer="Conv", consumers=1)
    not_fused = _layer(1000, 10**7, "Relu", "elementwise", producer="Conv", consumers=2)
    predictions = predict_layers([compute_heavy, memory_heavy, fused, not_fused], hardware)
    assert [p.bound for p in predictions] == ["compute", "memory", "fused", "memory"]
    expected = 2e9 / (665.6e9 * hardware.efficiency["conv"]) * 1e3 + hardware.overhead_us * 1e-3
    assert predictions[0].time_ms == pytest.approx(expected, rel=1e-9)
    assert predictions[1].time_ms == pytest.approx(8e7 / (59.7e9 * hardware.efficiency["elementwise"]) * 1e3 + 0.01, rel=1e-9)
    assert predictions[2].time_ms == 0.0
    fp16 = predict_layers([compute_heavy], hardware_model(load_profile("tx2"), "fp16", "maxn"))[0]
    assert fp16.compute_ms == pytest.approx(predictions[0].compute_ms / 2)


def test_fit_recovers_known_factors_on_synthetic_data():
    rng = random.Random(0)
    truth = FitResult({k: rng.uniform(1.0, 8.0) for k in KINDS}, 12e-6, 40e-6)
    rows = []
    for _ in range(60):
        row = {k: rng.uniform(0, 2e-3) if rng.random() < 0.5 else 0.0 for k in KINDS}
        row["layers"] = float(rng.randint(1, 40))
        row["run"] = 1.0
        rows.append(row)
    seconds = [truth.predict(row) for row in rows]
    prior = FitResult({k: 2.0 for k in KINDS}, 5e-6)  # deliberately wrong: the data must win
    exact = fit_factors(rows, seconds, prior, prior_weight=0.0)
    for kind in KINDS:
        assert exact.inverse_efficiency[kind] == pytest.approx(truth.inverse_efficiency[kind], rel=1e-6)
    assert exact.overhead_s == pytest.approx(truth.overhead_s, rel=1e-6)
    assert exact.run_overhead_s == pytest.approx(truth.run_overhead_s, rel=1e-6)
    pulled = fit_factors(rows, seconds, prior)  # the default weak prior moves the answer by little
    for kind in KINDS:
        assert pulled.inverse_efficiency[kind] == pytest.approx(truth.inverse_efficiency[kind], rel=0.02)
    # A kind the data never sees keeps the prior's figure.
    for row in rows:
        row["deform"] = 0.0
    seconds = [truth.predict(row) for row in rows]
    assert fit_factors(rows, seconds, prior).inverse_efficiency["deform"] == pytest.approx(2.0, rel=1e-3)


def test_micro_layers_time_what_the_x86_graphs_run():
    # The x86 graphs trace ELU as max(x, exp(clip(x, max=0)) - 1); timing the Elu op instead fitted the wrong cost.
    from toolkit.profiling.calibration import TINY_OPS, export_micro_layers

    graphs = export_micro_layers(32, 48)
    ops = {name: {node.op_type for node in graph.graph.node} for name, graph in graphs.items()}
    assert not any("Elu" in kinds for kinds in ops.values())
    assert {"Clip", "Exp", "Sub", "Max"} <= ops["(pointwise + elu) 16 @H x3"]
    tiny = graphs[f"{2 * TINY_OPS} tiny elementwise (overhead)"]  # pins the per-node overhead
    assert len([n for n in tiny.graph.node if n.op_type in ("Mul", "Add")]) == 2 * TINY_OPS


def test_a_network_the_fit_cannot_predict_is_named_with_its_terms():
    from toolkit.profiling.calibration import leave_one_out_note, unpredicted_terms

    row = {k: 0.0 for k in KINDS} | {"elementwise": 2e-3, "conv": 1e-3, "layers": 10.0, "run": 1.0}
    with_it = FitResult({k: 1.0 for k in KINDS}, 0.0, 1e-4)
    without = FitResult({k: 1.0 for k in KINDS} | {"elementwise": 0.4}, 0.0, 1e-4)
    assert unpredicted_terms(with_it, without, row) == ["elementwise 2.00 -> 0.80 ms"]
    entry = {"network": "featurenet", "measured_ms": 3.2, "relative_error": -0.34, "in_sample_predicted_ms": 3.1,
             "unpredicted_terms": ["elementwise 2.00 -> 0.80 ms"]}
    note = leave_one_out_note(entry)
    assert note.startswith("note: featurenet is predicted -34% off from the other graphs (limit 25%): the terms it "
                           "cannot predict are elementwise 2.00 -> 0.80 ms")
    assert leave_one_out_note(entry | {"relative_error": 0.2}) is None


def test_design_row_is_the_prediction_with_unit_efficiency():
    torch.manual_seed(0)
    _, _, layers = _keypoint_graph(FeatureNet(), 19, "native")
    hardware = hardware_model(load_profile("x86-cpu"))
    row = design_row(layers, hardware)
    factors = FitResult({k: 1.0 / hardware.efficiency[k] for k in KINDS}, hardware.overhead_us * 1e-6, hardware.run_overhead_us * 1e-6)
    layer_sum = sum(p.time_ms for p in predict_layers(layers, hardware))
    assert factors.predict(row) * 1e3 == pytest.approx(layer_sum + hardware.run_overhead_us * 1e-3, rel=1e-9)


def test_profile_cli_writes_report_with_measured_and_predicted(tmp_path, shared_data, capsys):
    torch.manual_seed(0)
    checkpoint = save_checkpoint(FeatureNet().eval(), tmp_path / "fn.safetensors")
    artefact = export_artefact(ExportOptions(target="x86-cpu", output=tmp_path / "art", checkpoint=checkpoint,
                                             input_size=SIZE, max_keypoints=100), log=lambda *_: None)
    out = tmp_path / "report"
    code = main(["profile", "--model", str(artefact), "--model", "featurenet-relu", "--target", "all", "--repeats", "3",
                 "--warmup", "1", "--no-calibration", "-o", str(out)])
    assert code == 0
    printed = capsys.readouterr().out
    assert "pred. tx2 MAXN fp16" in printed and "host ORT median" in printed
    report = json.loads((out / "profile.json").read_text())
    assert report["input_size"] == list(SIZE)  # taken from the artefact
    names = [m["name"] for m in report["models"]]
    assert names[-1] == "superpoint" and len(names) == 3
    labels = {hw["label"] for hw in report["hardware"]}
    assert labels == {"tx2 MAXN fp16", "tx2 MAXQ fp16", "x86-cpu fp32"}
    for model in report["models"]:
        for engine in ("onnxruntime", "torch-eager"):
            stats = model["measured_on_host"][engine]
            assert 0 < stats["median_ms"] <= stats["p90_ms"] and stats["threads"] == 1
        assert abs(model["targets"]["x86-cpu"]["onnx_vs_fvcore"]) < 0.01
        assert model["flops"] == 2 * model["macs"]
        for target in model["targets"].values():
            assert all(p["total_ms"] > 0 for p in target["predictions"].values())
            bounds = {layer["predicted"][label]["bound"] for layer in target["layers"] for label in layer["predicted"]}
            assert {"compute", "memory"} <= bounds
    assert report["models"][0]["targets"]["x86-cpu"]["graph"] == "artefact model.onnx"
    assert report["models"][0]["targets"]["tx2"]["opset"] == 13
    ratios = report["comparison"][names[0]]
    assert ratios["macs"] > 1 and ratios["measured onnxruntime"] > 0
    markdown = (out / "profile.md").read_text()
    assert "## Comparison" in markdown and "per-layer prediction" in markdown
    assert (out / "profile.png").read_bytes()[:4] == b"\x89PNG"


def test_calibrate_then_profile_uses_the_calibration(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))  # never the user's real cache
    calibration = tmp_path / "host.json"
    code = main(["profile", "--calibrate", "--input-size", "32x48", "--repeats", "3", "--warmup", "1",
                 "--calibration", str(calibration)])
    assert code == 0
    assert "leave-one-out" in capsys.readouterr().out
    data = json.loads(calibration.read_text())
    assert set(data["efficiency"]) == set(KINDS) and all(v > 0 for v in data["efficiency"].values())
    assert data["peak_gflops_fp32"] > 0 and data["memory_bandwidth_gbs"] > 0
    assert [e["network"] for e in data["leave_one_out"]] == ["featurenet", "featurenet-relu", "superpoint"]
    assert all(e["measured_ms"] > 0 and e["predicted_ms"] > 0 for e in data["leave_one_out"])
    assert not (tmp_path / "cache").exists()
    code = main(["profile", "--target", "x86-cpu", "--input-size", "32x48", "--repeats", "2", "--warmup", "0",
                 "--no-eager", "--calibration", str(calibration)])
    assert code == 0
    assert f"x86-cpu fp32 from {calibration}" in capsys.readouterr().out


def _fake_artefact(directory: Path, height: int, width: int) -> Path:
    from fake_graphs import constant_keypoint_graph, keypoint_outputs, write_graph_artefact

    return write_graph_artefact(directory, constant_keypoint_graph(height, width, keypoint_outputs()), height, width)


def test_bad_input_is_one_line_and_exit_2(tmp_path, capsys):
    assert main(["profile", "--target", "jetson-nano"]) == 2
    assert "unknown target 'jetson-nano'" in capsys.readouterr().err

    toml = load_profile("x86-cpu").source
    text = Path(toml).read_text().replace("memory_bandwidth_gbs", "# memory_bandwidth_gbs")
    broken = tmp_path / "broken.toml"
    broken.write_text(text)
    assert main(["profile", "--target", str(broken), "--input-size", "32x48"]) == 2
    err = capsys.readouterr().err
    assert "missing the field 'hardware.memory_bandwidth_gbs'" in err and len(err.strip().splitlines()) == 1

    artefact = _fake_artefact(tmp_path / "art", 240, 320)
    assert main(["profile", "--model", str(artefact), "--input-size", "480x640"]) == 2
    assert "exported for 240x320, not 480x640" in capsys.readouterr().err

    assert main(["profile", "--model", "resnet50"]) == 2
    assert "unknown model 'resnet50'" in capsys.readouterr().err
    assert main(["profile", "--calibrate", "--target", "tx2"]) == 2
    assert "--calibrate measures this host" in capsys.readouterr().err
