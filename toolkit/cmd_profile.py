"""`toolkit profile`: parameters, MACs/FLOPs, measured and predicted latency per target profile."""
from __future__ import annotations

import argparse
import os
from contextlib import nullcontext
from pathlib import Path

from toolkit.sizes import parse_size
from profiles import TargetProfile, load_profile
from toolkit.atomic import OutputClaim
from toolkit.errors import ToolkitError
from vo_runtime.machine import check_thread_count

EXAMPLES = """examples:
  toolkit profile                                         # the shipped model vs SuperPoint, both targets, 240x320
  toolkit profile --model default --model default-relu --target x86-cpu --threads 2
  toolkit profile --model featurenet --model featurenet-relu   # the architectures with random weights
  toolkit profile --model runs/a/best.safetensors --input-size 480x640 -o reports/a-480
  toolkit profile --model out/cpu --target x86-cpu        # an exported artefact (its own input size)
  toolkit profile --calibrate                             # fit this host's figures, report the LOO error
  toolkit profile --calibrate --calibration host.json && toolkit profile --calibration host.json

Counts: FLOPs = 2 x MACs. The ONNX-graph count is a cross-check of the fvcore count (same conventions).
Predictions: a per-layer roofline (peak compute / bandwidth of the target profile, efficiency per op kind).
The x86-cpu figures come from the calibration file when there is one, else from the shipped profile.
"""


def default_calibration_path() -> Path:
    """~/.cache/edgefeat/x86-cpu.calibration.json (or under $XDG_CACHE_HOME): user-writable, never the package."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "edgefeat" / "x86-cpu.calibration.json"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "profile",
        help="parameters, MACs/FLOPs, measured and predicted latency per target",
        description="Count parameters, MACs and FLOPs (fvcore, cross-checked on the exported ONNX graph), measure "
        "latency on this host (onnxruntime and torch eager) and predict it on each target with a per-layer "
        "roofline; compare with the SuperPoint architecture at the same resolution.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--model", action="append", metavar="M",
                        help="default / default-relu (the shipped weights), featurenet, featurenet-relu, superpoint (random "
                        "weights), a checkpoint or an artefact directory (repeatable; default: default)")
    parser.add_argument("--target", default="all", help="tx2, x86-cpu, all, or a profile TOML path (default all)")
    parser.add_argument("--input-size", metavar="HxW", help="input size (default: the artefact's, else the profile's)")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime/torch threads for host measurements (default 1)")
    parser.add_argument("--repeats", type=int, default=20, help="timed runs per model after warm-up (default 20)")
    parser.add_argument("--warmup", type=int, default=3, help="untimed runs first (default 3)")
    parser.add_argument("--no-eager", action="store_true", help="skip the torch eager reference timing")
    parser.add_argument("--no-compare", action="store_true", help="do not add the SuperPoint architecture for comparison")
    parser.add_argument("--calibrate", action="store_true", help="measure micro-layers and networks, fit this host's figures")
    parser.add_argument("--calibration", type=Path, metavar="FILE",
                        help=f"host calibration to write (--calibrate) or read (default {default_calibration_path()})")
    parser.add_argument("--no-calibration", action="store_true", help="ignore any calibration file; use the profile's figures")
    parser.add_argument("-o", "--output", type=Path, metavar="DIR", help="write profile.json, profile.md and profile.png here")
    parser.add_argument("--force", action="store_true",
                        help="replace a profile report written here before (never any other folder)")
    parser.set_defaults(func=run)


def _profiles(target: str) -> list[TargetProfile]:
    names = ["tx2", "x86-cpu"] if target == "all" else [target]
    return [load_profile(name) for name in names]


def _check_args(args: argparse.Namespace) -> None:
    check_thread_count(args.threads, "--threads", ToolkitError)
    if args.repeats < 1 or args.warmup < 0:
        raise ToolkitError("--repeats must be at least 1 and --warmup at least 0")


def _size(args: argparse.Namespace, sources, profiles: list[TargetProfile]) -> tuple[int, int]:
    if args.input_size:
        return parse_size(args.input_size, "--input-size")
    sizes = {s.artefact_size for s in sources if s.artefact_size is not None}
    if len(sizes) > 1:
        raise ToolkitError("the artefacts were exported for different input sizes: profile them separately or pass --input-size")
    return sizes.pop() if sizes else profiles[0].default_input_size


def run(args: argparse.Namespace) -> int:
    _check_args(args)
    profiles = _profiles(args.target)
    if args.calibrate:
        return _run_calibration(args, profiles)
    from toolkit.profiling.report import claim_report_dir

    inputs = [Path(spec) for spec in args.model or [] if Path(spec).exists()]
    # Claimed before minutes of measuring, not after, and held until the report is in place.
    with claim_report_dir(args.output, args.force, inputs) if args.output else nullcontext() as claim:
        return _profile(args, profiles, claim)


def _profile(args: argparse.Namespace, profiles: list[TargetProfile], claim: OutputClaim | None) -> int:
    """Measure and predict every model on every target; print the report and write it through ``claim``."""
    from toolkit.profiling.profile import build_report
    from toolkit.profiling.report import terminal_text, write_outputs
    from toolkit.profiling.roofline import hardware_model, load_calibration
    from toolkit.profiling.sources import resolve_model

    requested = parse_size(args.input_size, "--input-size") if args.input_size else None
    specs = list(args.model or ["default"])
    if not args.no_compare and "superpoint" not in specs:
        specs.append("superpoint")
    sources = [resolve_model(spec, requested) for spec in specs]
    size = _size(args, sources, profiles)
    calibration_path = args.calibration or default_calibration_path()
    calibration = None if args.no_calibration else load_calibration(calibration_path)
    if args.calibration and calibration is None and not args.no_calibration:
        raise ToolkitError(f"calibration file not found: {args.calibration}")
    hardware = {}
    for profile in profiles:
        modes = profile.hardware.get("power_modes") or [None]
        host_calibration = calibration if profile.name == "x86-cpu" else None
        hardware[profile.name] = [hardware_model(profile, None, mode, host_calibration) for mode in modes]
    report = build_report(sources, profiles, hardware, size, args.threads, args.repeats, args.warmup, not args.no_eager)
    if calibration is not None:
        report["calibration"] = {"path": calibration["path"], "threads": calibration.get("threads"),
                                 "leave_one_out": calibration.get("leave_one_out", [])}
    print(terminal_text(report))
    if calibration is not None and calibration.get("threads") not in (None, args.threads):
        print(f"note: the calibration was measured with {calibration['threads']} thread(s), this run uses {args.threads}")
    if claim is not None:
        write_outputs(report, claim)
        print(f"wrote {args.output}/profile.json, profile.md, profile.png")
    return 0


def _check_calibration_target(path: Path) -> None:
    """The calibration file is written only where nothing is, or over an earlier calibration file."""
    from toolkit.atomic import check_output_path
    from toolkit.profiling.roofline import load_calibration

    check_output_path(path)
    if path.is_dir():
        raise ToolkitError(f"--calibration {path} is a directory; name a .json file")
    if path.exists():
        try:
            load_calibration(path)
        except ToolkitError:
            raise ToolkitError(f"refusing to overwrite {path}: it is not a calibration file written by "
                               "toolkit profile --calibrate") from None


def _run_calibration(args: argparse.Namespace, profiles: list[TargetProfile]) -> int:
    from toolkit.profiling.calibration import calibrate, leave_one_out_note
    from toolkit.profiling.profile import target_graph
    from toolkit.profiling.report import format_table
    from vo_runtime.atomic_file import write_json_atomic
    from toolkit.profiling.roofline import hardware_model
    from toolkit.profiling.sources import ARCHITECTURES, resolve_model

    host = next((p for p in profiles if p.name == "x86-cpu"), None)
    if host is None:
        raise ToolkitError("--calibrate measures this host: use --target x86-cpu (or all)")
    if args.model:
        raise ToolkitError("--calibrate uses its own set of networks (featurenet, featurenet-relu, superpoint); drop --model")
    height, width = parse_size(args.input_size, "--input-size") if args.input_size else host.default_input_size
    path = args.calibration or default_calibration_path()
    _check_calibration_target(path)
    prior = hardware_model(host)  # the shipped figures: the fit's fallback where the data is silent
    networks = {name: target_graph(resolve_model(name, None), host, height, width).model for name in ARCHITECTURES}
    result = calibrate(networks, height, width, args.threads, args.repeats, args.warmup, prior)
    write_json_atomic(path, result.to_json_dict() | {"input_size": [height, width]})
    caches = ", ".join(f"{c['bytes'] >> 10} KiB: {c['bandwidth_gbs']:.1f} GB/s" for c in result.cache_levels)
    print(f"host {result.host}, {args.threads} thread(s), {height}x{width}: peak {result.peak_gflops_fp32:.1f} GFLOP/s "
          f"(MatMul), DRAM {result.memory_bandwidth_gbs:.1f} GB/s, caches [{caches}] (Add), overhead {result.overhead_us:.1f} us/layer")
    print("efficiency per kind: " + ", ".join(f"{k} {v:.3g}" for k, v in result.efficiency.items()))
    rows = [[e["network"], f"{e['measured_ms']:.2f}", f"{e['predicted_ms']:.2f}", f"{e['relative_error']:+.1%}",
             f"{e['in_sample_predicted_ms']:.2f}"] for e in result.leave_one_out]
    print(format_table(["network", "measured ms", "predicted ms (leave-one-out)", "error", "predicted ms (all data)"], rows))
    mean_abs = sum(abs(e["relative_error"]) for e in result.leave_one_out) / len(result.leave_one_out)
    print(f"mean absolute leave-one-out error: {mean_abs:.1%}")
    for note in filter(None, map(leave_one_out_note, result.leave_one_out)):
        print(note)
    print(f"wrote {path}")
    return 0
