"""`toolkit prune`: structured channel pruning of a FeatureNet checkpoint, then distillation fine-tuning."""
from __future__ import annotations

import argparse
from pathlib import Path

from toolkit.sizes import parse_size
from toolkit.compression.workflow import PruneOptions, format_report, prune_checkpoint

EXAMPLES = """examples:
  toolkit prune --checkpoint default-relu --ratio 0.5 -o relu-pruned50.safetensors    # the shipped ReLU model
  toolkit prune --checkpoint runs/a/best.safetensors --ratio 0.3 -o runs/a/pruned30.safetensors
  toolkit prune --checkpoint C --target-macs 150000000 --steps 300          # MACs at --size (240x320)
  toolkit prune --checkpoint C --ratio 0.5 --images ../shared/data/train_images --labels labels/sp --steps 500

Channels are removed group by group (DepGraph keeps coupled layers consistent; the deformable conv's
offset/mask outputs and the 65-logit / descriptor outputs never shrink), counts rounded to multiples of 8.
The pruned model is fine-tuned by distillation from the unpruned one (plus the SuperPoint training loss when
--labels is given) and saved as a normal checkpoint; export it with `toolkit export`. The report (params,
MACs, latency, drift from the unpruned outputs) is printed and stored in the checkpoint metadata and
beside it as <output>.json.
"""


def _ratio(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "prune",
        help="prune a checkpoint's channels (torch-pruning DepGraph) and fine-tune it by distillation",
        description="Structured channel pruning of a FeatureNet checkpoint, distillation fine-tuning from the "
        "unpruned model, and a before/after report of parameters, MACs, latency and output drift.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="FeatureNet checkpoint (.safetensors); default: the shipped featurenet-elu "
                        "(`default-relu` names the shipped ReLU model)")
    amount = parser.add_mutually_exclusive_group(required=True)
    amount.add_argument("--ratio", type=_ratio, help="fraction of channels to remove per group, in (0, 1)")
    amount.add_argument("--target-macs", type=int, metavar="M", help="smallest pruning that needs at most M MACs at --size")
    parser.add_argument("--images", type=Path, metavar="DIR", help="images to distil on (default: train_images/ under $EDGEFEAT_DATA, else ../shared/data)")
    parser.add_argument("--labels", type=Path, metavar="L", help="`toolkit label` folder for --images: adds the training loss")
    parser.add_argument("--steps", type=int, default=100, help="distillation steps (default 100; 0 skips fine-tuning)")
    parser.add_argument("--batch", type=int, default=4, help="images per step (default 4)")
    parser.add_argument("--lr", type=float, default=1e-4, help="Adam learning rate (default 1e-4)")
    parser.add_argument("--size", metavar="HxW", default="240x320", help="distillation and measurement size (default 240x320)")
    parser.add_argument("-o", "--output", type=Path, metavar="OUT", help="pruned checkpoint (default <checkpoint>-pruned<pct>.safetensors)")
    parser.add_argument("--force", action="store_true",
                        help="replace a pruned checkpoint and report written before (never the source or other files)")
    parser.add_argument("--no-eval", action="store_true", help="skip the evaluation metrics (HPatches v_dogman, LOL pairs)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = PruneOptions(
        checkpoint=args.checkpoint, output=args.output, ratio=args.ratio, target_macs=args.target_macs,
        images=args.images, labels=args.labels, steps=args.steps, size=parse_size(args.size), batch=args.batch,
        lr=args.lr, force=args.force, evaluate=not args.no_eval,
    )
    report = prune_checkpoint(options)  # writes the checkpoint and its .json report
    print(format_report(report))
    print(f"wrote {report.output} (export it with: toolkit export --target <tx2|x86-cpu> --checkpoint {report.output} -o DIR)")
    return 0
