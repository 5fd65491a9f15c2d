"""`toolkit train`: self-supervised training of the network from teacher labels and warped pairs."""
from __future__ import annotations

import argparse
import os
from contextlib import nullcontext
from pathlib import Path

from toolkit.atomic import locked_output_dir
from vo_runtime.machine import check_thread_count
from toolkit.training.trainer import TrainConfig, read_config_file, resolve_config, train

EPILOG = """examples:
  toolkit label --teacher alike-n --images ../shared/data/train_images --out labels/distill \
      --num-homographies 1 --max-keypoints 1024 --nms-radius 2 --descriptors
  toolkit train --images ../shared/data/train_images --labels labels/distill --out runs/fn1 --threads 2
  toolkit train --images photos/ --labels labels/st --config train.toml --batch 16 --out runs/fn2
  toolkit train --images photos/ --labels labels/st --out runs/fn2 --resume --steps 40000
  torchrun --nproc_per_node 4 -m toolkit train --images photos/ --labels labels/st --out runs/ddp

--config takes a JSON or TOML file with any TrainConfig field (recipe = "distill" | "paper", arch, model,
steps, batch, lr, lr_schedule, threads, cpu_bf16, homography, augment, loss, distill, scales, validation,
...). The distill recipe (default) needs labels made with --descriptors by an ALIKE teacher. --resume continues the
run in --out from its last checkpoint with the run's own config (--steps may raise the total).
"""


def run(args: argparse.Namespace) -> int:
    from toolkit.errors import ToolkitError

    if args.resume and args.config:
        raise ToolkitError("--config cannot be combined with --resume: a resumed run keeps its own config")
    run_dir = Path(args.out)
    # One training per run folder at a time, from the first check to the end. Under torchrun every process runs
    # this command for the same folder: the first (RANK 0, which writes it) holds the lock for them all.
    lock = locked_output_dir(run_dir) if os.environ.get("RANK", "0") == "0" else nullcontext()
    with lock:
        return _train_into(args, run_dir)


def _train_into(args: argparse.Namespace, run_dir: Path) -> int:
    from toolkit.errors import ToolkitError

    config = read_config_file(args.config) if args.config else TrainConfig()
    config = resolve_config(run_dir, args.resume, config, args.steps, args.batch)
    if args.workers is not None:  # allowed on --resume too: samples do not depend on the worker count
        check_thread_count(args.workers, "--workers", ToolkitError, allow_zero=True)  # processes, one a core
        config.num_workers = args.workers
    if args.threads is not None:  # also on --resume: results do not depend on it
        check_thread_count(args.threads, "--threads", ToolkitError)
        config.threads = args.threads
    result = train(config, args.images, args.labels, run_dir, resume=args.resume)
    if result["rank"] != 0:  # under torchrun only the first process reports
        return 0
    last, val = result["last"], result["validation"]
    line = f"trained to step {result['step']} on {result['train_images']} images ({result['val_images']} held back)"
    if last:
        line += f", loss {last['loss']:.4f}"
    if val:
        line += (f", val matching score {val['matching_score']:.3f}, NN mAP {val['nn_map']:.3f}, "
                 f"repeatability {val['repeatability']:.3f}, localisation {val['localisation_error']:.2f} px")
    if result["unreadable"]:
        line += f"; {result['unreadable']} unreadable files skipped"
    print(f"{line} -> {run_dir}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "train",
        help="train the network from a teacher (homographic pairs; distill or paper recipe)",
        description="Train the keypoint network without hand labels: keypoint cross-entropy against the "
        "teacher's keypoints on both views of a random homographic pair, plus (distill, the default) the "
        "teacher's descriptors and InfoNCE across views at several input sizes, or (paper) the descriptor "
        "hinge loss. One GPU, several under torchrun (DDP), or a CPU (gloo; bfloat16 autocast where the CPU "
        "has native bfloat16, else float32).",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--images", required=True, help="folder of images (the one given to `toolkit label`)")
    parser.add_argument("--labels", required=True, help="label folder written by `toolkit label`")
    parser.add_argument("--config", default=None, help="JSON or TOML file of TrainConfig fields")
    parser.add_argument("--steps", type=int, default=None, help="total optimisation steps (default 20000)")
    parser.add_argument("--batch", type=int, default=None, help="pairs per step per process (default 8)")
    parser.add_argument("--out", default="runs/train", help="run folder (default runs/train)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch CPU threads (default: torch's choice; on a shared 2-core box use 1)")
    parser.add_argument("--workers", type=int, default=None, help="DataLoader worker processes (default: 4 on CUDA, 0 on CPU)")
    parser.set_defaults(func=run)
