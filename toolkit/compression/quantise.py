"""Quantising an exported artefact: INT8 (x86-cpu, onnxruntime static QDQ) or FP16 (weights in FP16).

INT8 follows what measured well on this graph: only Conv, the ReLU after it and the descriptor projection
(Gemm) are quantised (the deformable conv, ELU, softmax and top-K stay float; with ReLU included the Q/DQ
pair sits after the ReLU, so the uint8 range is not half spent on negatives that ReLU discards), weights
per output channel int8, activations uint8 calibrated on real images at the 99.99th percentile of each
tensor's values (MinMax let the brightest images set every range and cost 0.026 in matching score on raw
low-light pairs; the percentile 0.016, measured on the shipped ReLU model). Three kinds of conv stay
float: the keypoint logits' output convs (they feed a softmax threshold), the fixed-kernel convs that
normalise each cell's pixels, and the single-channel stem (slow as QLinearConv). ``keep_sensitive`` also
keeps the N convs with the largest isolated error in float.
The result is a new artefact directory with its own manifest; the FP32 artefact is not touched.
"""
from __future__ import annotations

import json
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

from export.artefact import MIN_IDENTICAL
from export.artefact_graph import load_artefact_graph
from export.half import to_fp16
from export.checks import check_against_profile, require_non_negative_gathers
from export.graph_order import topologically_sorted
from export.onnx_export import check_before_writing, op_histogram
from export.parity import default_parity_paths, prepare_image
from export.reference import reference_images, write_cpu_references
from profiles import TargetProfile, load_profile
from toolkit import __version__
from export.parity import SHIPPED_PARITY_DIR
from toolkit.compression.images import load_images
from toolkit.compression.report import interleaved_median_ms, ort_drift, ort_session
from toolkit.compression.sensitivity import fixed_kernel_convs, head_output_convs, layer_sensitivity, single_channel_convs
from toolkit.atomic import OutputClaim, OutputKind, claim_output_dir
from toolkit.errors import ToolkitError
from vo_runtime.artefact import MANIFEST_NAME, MODEL_NAME, sha256_file

MODES = ("int8", "fp16")
# Gemm is the descriptor projection at the keypoints. The default list also quantises the sampling
# arithmetic: ~8 % heatmap error.
QUANTISED_OPS = ("Conv", "Relu", "Gemm")
CALIBRATION_PERCENTILE = 99.99
SENSITIVITY_IMAGES = 8  # isolated per-layer errors settle after a few images


@dataclass
class QuantiseOptions:
    artefact: Path
    mode: str
    output: Path
    calibration: Path | None = None
    calibration_count: int = 32
    keep_sensitive: int = 0
    force: bool = False
    timing_repeats: int = 20


class _ImageReader:
    """onnxruntime CalibrationDataReader over prepared images [N, 1, H, W]."""

    def __init__(self, input_name: str, images: np.ndarray) -> None:
        self.feeds = iter([{input_name: image[None]} for image in images])

    def get_next(self):
        return next(self.feeds, None)

    def rewind(self):  # pragma: no cover - onnxruntime's API; one pass is all calibration needs
        pass


def _name_unnamed_nodes(model: onnx.ModelProto) -> None:
    """nodes_to_exclude works by node name; give anonymous nodes stable ones."""
    for index, node in enumerate(model.graph.node):
        if not node.name:
            node.name = f"{node.op_type}_{index}"


def _preprocess(model_path: Path, work: Path) -> Path:
    """onnxruntime's quant_pre_process (shape inference + graph cleanup); the raw graph if it refuses."""
    from onnxruntime.quantization.shape_inference import quant_pre_process

    target = work / "pre.onnx"
    try:
        quant_pre_process(str(model_path), str(target), skip_symbolic_shape=True)  # symbolic pass fails on these graphs
        return target
    except Exception:  # an optional optimisation: quantising the raw graph is still correct
        return model_path


def quantise_int8(model: onnx.ModelProto, calibration: np.ndarray, exclude: list[str]) -> onnx.ModelProto:
    """Static QDQ INT8 (per-channel S8 weights, U8 activations, percentile calibration) of the
    `QUANTISED_OPS` nodes not in ``exclude``; sorted, as the inserted Q/DQ nodes are not placed in order
    by contract."""
    from onnxruntime.quantization import CalibrationMethod, QuantFormat, QuantType, quantize_static

    with tempfile.TemporaryDirectory(prefix="edgefeat-quant-") as work:
        work_dir = Path(work)
        source = work_dir / "fp32.onnx"
        onnx.save(model, str(source))
        prepared = _preprocess(source, work_dir)
        target = work_dir / "int8.onnx"
        quantize_static(
            str(prepared), str(target), _ImageReader(model.graph.input[0].name, calibration),
            quant_format=QuantFormat.QDQ, per_channel=True, activation_type=QuantType.QUInt8,
            weight_type=QuantType.QInt8, op_types_to_quantize=list(QUANTISED_OPS), nodes_to_exclude=list(exclude),
            calibrate_method=CalibrationMethod.Percentile, extra_options={"CalibPercentile": CALIBRATION_PERCENTILE},
        )
        return topologically_sorted(onnx.load(str(target)))


def quantise_fp16(model: onnx.ModelProto) -> onnx.ModelProto:
    """FP16 weights and arithmetic, FP32 inputs and outputs (Cast at the edges), post-processing in FP32."""
    return to_fp16(model)


# What --force may replace: an artefact this command wrote before, as its listing records (vo_runtime.outputs).
QUANTISED_ARTEFACT = OutputKind("quantised-artefact", "a quantised artefact written by toolkit quantise")


def _parity_images(height: int, width: int) -> tuple[np.ndarray, list[str]]:
    paths = default_parity_paths()
    return np.concatenate([prepare_image(path, height, width) for path in paths]), [p.name for p in paths]


def quantise_artefact(options: QuantiseOptions, log=print) -> Path:
    """Quantise ``options.artefact`` into ``options.output``; returns the new artefact directory."""
    if options.mode not in MODES:
        raise ToolkitError(f"--mode must be one of {', '.join(MODES)}, got {options.mode!r}")
    source = Path(options.artefact)
    manifest, model = load_artefact_graph(source)  # ArtefactError (exit 2): missing, checksum, or a bad graph
    if not isinstance(manifest.get("target"), str):
        raise ToolkitError(f"{source}/manifest.json names no target profile: re-export the artefact")
    profile = load_profile(manifest["target"])
    if options.mode == "int8" and profile.name == "tx2":
        raise ToolkitError("int8 is refused for tx2: its Pascal GPU has no fast INT8 path (INT8 engines ran slower "
                           "than FP16); use --mode fp16")
    if options.mode == "int8" and not profile.runtime.startswith("onnxruntime"):
        raise ToolkitError(f"int8 needs an onnxruntime target; {profile.name} runs {profile.runtime}")
    if manifest.get("precision_applied") == "tensorrt-build-flag":  # the tx2 default: FP16 is trtexec --fp16
        raise ToolkitError(f"{source} is already an FP16 artefact for TensorRT (trtexec --fp16 builds its FP32 graph in "
                           "FP16 on the device): deploy it as it is; for FP16 weights in the file, export with "
                           "--precision fp32 and quantise that")
    if manifest.get("precision_applied", "fp32") != "fp32":
        raise ToolkitError(f"{source} is already {manifest.get('precision_applied')}; quantise the FP32 artefact")
    if options.calibration_count < 1:
        raise ToolkitError(f"--calibration-count must be >= 1, got {options.calibration_count}")
    if options.keep_sensitive < 0:
        raise ToolkitError(f"--keep-sensitive must be >= 0, got {options.keep_sensitive}")
    output = Path(options.output)
    if output.resolve() == source.resolve():
        raise ToolkitError("the quantised artefact needs its own directory (-o must differ from --artefact)")
    with claim_output_dir(output, QUANTISED_ARTEFACT, options.force, [source, options.calibration]) as claim:
        _quantise_into(claim, options, source, manifest, model, profile, log)
    return output


def _quantise_into(claim: OutputClaim, options: QuantiseOptions, source: Path, manifest: dict, model: onnx.ModelProto,
                   profile: TargetProfile, log) -> None:
    """Quantise, check and measure, then write the new artefact through ``claim`` (held by the caller)."""
    _name_unnamed_nodes(model)
    height, width = manifest["input"]["shape"][2:]

    details: dict = {"mode": options.mode}
    if options.mode == "int8":
        folder = Path(options.calibration) if options.calibration else SHIPPED_PARITY_DIR
        calibration, paths = load_images(folder, options.calibration_count, (height, width))
        log(f"calibrating on {len(paths)} images from {folder}")
        sensitivity = layer_sensitivity(model, calibration[:SENSITIVITY_IMAGES])
        float_nodes = {"head_outputs": head_output_convs(model), "fixed_kernels": fixed_kernel_convs(model),
                       "single_channel": single_channel_convs(model)}
        always_float = [name for names in float_nodes.values() for name in names]
        candidates = [item.node for item in sensitivity if item.node not in always_float]
        kept = candidates[: options.keep_sensitive]
        quantised = quantise_int8(model, calibration, always_float + kept)
        precision_applied = "onnx-int8-qdq"
        details.update({
            "scheme": f"static QDQ of {'+'.join(QUANTISED_OPS)}, per-channel int8 weights, uint8 activations, percentile {CALIBRATION_PERCENTILE} calibration",
            "calibration": {"folder": str(folder), "count": len(paths), "requested": options.calibration_count,
                            "images": [str(p.relative_to(folder)) for p in paths]},
            "float_nodes": {**float_nodes, "sensitive": kept},
            "sensitivity": [item.to_dict() for item in sensitivity],
            "sensitivity_images": min(len(paths), SENSITIVITY_IMAGES),
        })
        activation = manifest.get("model", {}).get("config", {}).get("activation")
        if activation == "elu":
            log("note: ELU stays float in onnxruntime, so this INT8 graph is barely faster; the ReLU deploy variant "
                "(checkpoint with activation relu) quantises end to end")
    else:
        quantised = quantise_fp16(model)
        precision_applied = "onnx-fp16-weights"
        details["scheme"] = "float16 weights and arithmetic, float32 inputs/outputs (keep_io_types)"
    check_against_profile(quantised, profile)  # names the first op the target cannot run
    checker = check_before_writing(quantised, f"the {options.mode} graph")  # before the parity run: it takes milliseconds

    images, names = _parity_images(height, width)
    reference, candidate = ort_session(model), ort_session(quantised)
    drift = ort_drift(reference, candidate, images)
    if options.mode == "fp16":
        # FP16 index arithmetic is exact only below 2048: prove the gathers still read where they should.
        details["min_gather_index"] = require_non_negative_gathers(quantised, [image[None] for image in images], profile)
        if drift.keypoints_unchanged < MIN_IDENTICAL["fp16"]:  # NaN (dense graphs) compares False
            raise ToolkitError(f"fp16 parity failed: only {drift.keypoints_unchanged:.1%} of keypoints unchanged "
                               f"against FP32 (need {MIN_IDENTICAL['fp16']:.0%})")
    feed = {reference.get_inputs()[0].name: images[:1]}
    timings = interleaved_median_ms({"fp32": lambda: reference.run(None, feed), options.mode: lambda: candidate.run(None, feed)},
                                    repeats=options.timing_repeats)
    details["parity_vs_fp32"] = {**drift.to_dict(), "images": names}
    details["latency_ms_1thread"] = {**{k: round(v, 3) for k, v in timings.items()},
                                     "speedup": round(timings["fp32"] / timings[options.mode], 3)}

    new_manifest = json.loads(json.dumps(manifest))
    new_manifest.update({
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "toolkit_version": __version__,
        "precision": options.mode,
        "precision_applied": precision_applied,
        "source_artefact": {"path": str(source), "onnx_sha256": manifest["onnx"]["sha256"]},
        "quantisation": details,
    })
    with claim.writing() as staging:
        onnx.save(quantised, str(staging / MODEL_NAME))
        new_manifest["onnx"] = {**manifest["onnx"], "file": MODEL_NAME, "sha256": sha256_file(staging / MODEL_NAME),
                                "op_types": op_histogram(quantised), "checker": checker,
                                # the source's graphs padded for channel blocks are float: this artefact is one graph
                                "block_graphs": []}
        # this graph's own outputs on the parity images, for `python -m vo_runtime verify`
        new_manifest["reference"] = write_cpu_references(staging, MODEL_NAME, reference_images(default_parity_paths(), height, width),
                                                         float(manifest["input"]["normalisation"]["scale"]), manifest["mode"])
        (staging / MANIFEST_NAME).write_text(json.dumps(new_manifest, indent=2) + "\n")
        (staging / "README.md").write_text(_readme(new_manifest))


def _readme(manifest: dict) -> str:
    q = manifest["quantisation"]
    parity = q["parity_vs_fp32"]
    lines = [
        f"# EdgeFeat artefact: {manifest['model']['arch']} for {manifest['target']}, {manifest['precision'].upper()}",
        "",
        f"Quantised from the FP32 artefact (model.onnx sha256 `{manifest['source_artefact']['onnx_sha256']}`): {q['scheme']}.",
        f"- input `image` {manifest['input']['shape']} float32, grayscale / 255; outputs as the FP32 artefact (float32)",
        f"- model.onnx sha256: `{manifest['onnx']['sha256']}`",
    ]
    if "calibration" in q:
        lines.append(f"- calibrated on {q['calibration']['count']} images from `{q['calibration']['folder']}`; "
                     f"float convs: {', '.join(q['float_nodes']['head_outputs'] + q['float_nodes']['sensitive'])}")
    lines += [
        f"- against FP32 on {len(parity['images'])} real images: {parity['keypoints_unchanged']:.2%} keypoints unchanged, "
        f"descriptor cosine {parity['descriptor_cosine']:.4f}",
        f"- latency (onnxruntime, 1 thread, median): FP32 {q['latency_ms_1thread']['fp32']} ms, "
        f"{manifest['precision'].upper()} {q['latency_ms_1thread'][manifest['precision']]} ms",
        "",
    ]
    if manifest["target"] == "tx2":  # TensorRT engines are built on the device itself
        lines += ["On the TX2 (JetPack 4.6, MAXN): `/usr/src/tensorrt/bin/trtexec --onnx=model.onnx --fp16 "
                  "--workspace=1024 --saveEngine=model_fp16.engine`.", ""]
    else:
        lines += ["Load it like any artefact: `vo_runtime.FeatureExtractor(\"path/to/this/directory\")`.", ""]
    return "\n".join(lines)
