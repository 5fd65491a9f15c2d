"""`toolkit eval synth`: generate HPatches-style sequences from folders of frames and evaluate models on them,
with bootstrap intervals over sequences (the generator: `toolkit.evaluation.synth`)."""
from __future__ import annotations

import argparse
import os
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from toolkit.atomic import OutputClaim, OutputKind, claim_output_dir
from toolkit.eval_common import add_common_options, base_report, evaluate_models, finish_report, load_detectors, \
    protocol_configs
from toolkit.errors import ToolkitError
from toolkit.evaluation.intervals import BootstrapSettings, add_intervals
from toolkit.evaluation.report import claim_report_dir
from toolkit.evaluation.runner import ImageCache, ModelResult, group_summaries
from toolkit.evaluation.synth import (DEFAULT_SEQUENCES, KINDS, SynthConfig, SynthSequence, describe,
                                      generate_sequences, in_memory_pairs, write_sequences)
from toolkit.evaluation.synth_frames import find_frames
from toolkit.sizes import parse_hxw

SYNTH_EPILOG = f"""\
examples:
  toolkit eval synth --images ../shared/data/tum_fr2_desk_snippet --model default sift -o reports/tum
  toolkit eval synth --images my_frames/ --sequences 20 --kinds viewpoint --model orb --write synth_set/
  toolkit eval hpatches --data synth_set/ --model orb        (the written set: the same numbers)

Each source frame gives a sequence of a reference crop and 5 targets, easy to hard: viewpoint (group v: random
homographies, the target rendered from the whole frame, no borders) or darkness (group dark: gamma, gain,
vignetting, a light on the camera, shot and read noise, motion blur; identity homography). Sequences are seeded
from --seed and each frame's content: the same frames give the same sequences. Every number gets a 95 %
bootstrap interval over sequences (1000 resamples). Default {DEFAULT_SEQUENCES} sequences per kind (5 pairs each).
--write DIR saves them in HPatches layout. Details: docs/evaluation.md.
"""

SYNTH_SET = OutputKind("synth-sequences", "a set of sequences written by toolkit eval synth")
BOOTSTRAP_RESAMPLES = 1000


def register_synth(sub: argparse._SubParsersAction) -> None:
    parser = sub.add_parser("synth", help="HPatches-style sequences generated from any folders of frames",
                            description="Generate viewpoint and darkness sequences from folders of frames and "
                                        "evaluate models on them, with bootstrap intervals over sequences.",
                            epilog=SYNTH_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--images", required=True, nargs="+", action="extend", type=Path, metavar="DIR",
                        help="folders searched recursively for .png/.jpg/.jpeg/.ppm/.bmp frames")
    add_common_options(parser, data=False)
    parser.add_argument("--seed", type=int, default=0, help="seed of the sequences and the intervals (default 0)")
    parser.add_argument("--sequences", type=int, default=DEFAULT_SEQUENCES, metavar="N",
                        help=f"sequences per kind, frames picked evenly over all inputs (default {DEFAULT_SEQUENCES})")
    parser.add_argument("--kinds", nargs="+", choices=tuple(KINDS), default=list(KINDS),
                        help="which kinds of sequence (default both)")
    parser.add_argument("--render-size", default="480x640", metavar="HxW",
                        help="size the sequences are rendered and written at (default 480x640); the evaluation "
                             "resizes them to --size")
    parser.add_argument("--write", type=Path, default=None, metavar="DIR",
                        help="also save the sequences in HPatches layout (DIR/<seq>/1.png..6.png, H_1_k)")
    parser.set_defaults(func=run_synth)


def synth_config(args: argparse.Namespace) -> SynthConfig:
    """The checked generation options; `ToolkitError` for a bad value."""
    if args.sequences < 1:
        raise ToolkitError(f"--sequences must be at least 1, got {args.sequences}")
    if args.seed < 0:
        raise ToolkitError(f"--seed must be >= 0, got {args.seed}")
    kinds = tuple(kind for kind in KINDS if kind in args.kinds)
    return SynthConfig(seed=args.seed, sequences=args.sequences, kinds=kinds,
                       out_size=parse_hxw(args.render_size, "--render-size"))


def _check_outputs_apart(output: Path | None, write: Path | None) -> None:
    """-o and --write are two folders, neither inside the other (each is replaced as a whole)."""
    if output is None or write is None:
        return
    paths = [os.path.realpath(output), os.path.realpath(write)]
    if paths[0] == paths[1] or any(a.startswith(b.rstrip(os.sep) + os.sep) for a, b in (paths, paths[::-1])):
        raise ToolkitError(f"-o {output} and --write {write} must be two separate folders")


def run_synth(args: argparse.Namespace) -> int:
    config, detector_config = protocol_configs(args)
    synth = synth_config(args)
    frames = find_frames(args.images)
    _check_outputs_apart(args.output, args.write)
    with ExitStack() as stack:
        report_claim = stack.enter_context(claim_report_dir(args.output, args.images)) if args.output else None
        write_claim = (stack.enter_context(claim_output_dir(args.write, SYNTH_SET, True, args.images))
                       if args.write else None)
        detectors = load_detectors(args.model, detector_config)
        started = time.perf_counter()
        sequences = generate_sequences(frames, synth)
        print(f"generated {_counts(sequences)} from {len(frames)} frames in {time.perf_counter() - started:.1f} s")
        description = describe(frames, sequences, synth)
        if write_claim is not None:
            _write(write_claim, sequences, description)
        pairs, images = in_memory_pairs(sequences)
        bootstrap = BootstrapSettings(resamples=BOOTSTRAP_RESAMPLES, seed=synth.seed)
        report = base_report(args, [str(folder.resolve()) for folder in args.images], config)
        report["protocol"]["bootstrap"] = bootstrap.to_dict()
        report["synth"] = description
        report["notes"] = [f"{_counts(sequences)} generated from {len(frames)} frames (seed {synth.seed}, rendered "
                           f"at {synth.out_size[0]}x{synth.out_size[1]}). In brackets: 95 % bootstrap interval "
                           f"over sequences ({bootstrap.resamples} resamples, percentile)."]

        def summarise(result: ModelResult) -> dict[str, Any]:
            summaries = group_summaries(result)
            add_intervals(summaries, result, bootstrap)
            return summaries

        report, examples = evaluate_models(detectors, pairs, ImageCache(config.size, config.normalise,
                                                                         lambda path: images[str(path)]),
                                           config, report, summarise)
        finish_report(report, examples, report_claim, args.output)
    return 0


def _counts(sequences: list[SynthSequence]) -> str:
    """``"60 viewpoint and 60 darkness sequences (600 pairs)"``."""
    kinds = [f"{sum(s.kind == kind for s in sequences)} {kind}" for kind in KINDS if any(s.kind == kind
                                                                                      for s in sequences)]
    pairs = sum(len(s.homographies) for s in sequences)
    return f"{' and '.join(kinds)} sequences ({pairs} pairs)"


def _write(claim: OutputClaim, sequences: list[SynthSequence], description: dict[str, Any]) -> None:
    with claim.writing() as staging:
        write_sequences(staging, sequences, description)
    print(f"wrote {claim.path}: {len(sequences)} sequences in HPatches layout")
