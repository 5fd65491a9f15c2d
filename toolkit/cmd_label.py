"""`toolkit label`: teacher keypoint labels for an image folder by homographic adaptation."""
from __future__ import annotations

import argparse
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from toolkit.atomic import locked_output_dir
from toolkit.errors import ToolkitError
from toolkit.sizes import parse_size
from vo_runtime.machine import available_cores, check_thread_count
from toolkit.training.adaptation import AdaptationConfig, label_image, label_image_with_descriptors
from toolkit.training.label_store import LabelStore, find_images, read_image
from vo_runtime.progress import format_duration, progress_bar

EPILOG = """examples:
  toolkit label --teacher alike-n --images ../shared/data/train_images --out labels/alike-n
  toolkit label --teacher shi-tomasi --images photos/ --out labels/st --num-homographies 50 --size 120x160
  toolkit label --teacher alike-n --images ../shared/data/train_images --out labels/distill \
      --num-homographies 1 --max-keypoints 1024 --nms-radius 2 --descriptors     # the distill recipe's cache
  toolkit label --teacher superpoint:~/weights/superpoint_v1.pth --images photos/ --out labels/sp

An interrupted run continues where it stopped when rerun with the same arguments; a folder made with
another teacher or other settings is refused.
"""


@dataclass
class LabelSummary:
    labelled: int
    skipped: int  # already in the store
    unreadable: int
    seconds: float

    @property
    def images_per_second(self) -> float:
        return self.labelled / self.seconds if self.seconds > 0 else 0.0


MAX_HOMOGRAPHIES = 1000  # warps per image; the paper's adaptation used 100
LONG_RUN_S = 3600.0  # an estimate past an hour gets a warning line (a 24 h run once started without one)
ESTIMATE_AFTER = 3  # images labelled before the estimate is trusted


def cost_warning(seconds_per_image: float, remaining: int, config: AdaptationConfig, device: torch.device) -> str | None:
    """One warning line when labelling the ``remaining`` images will take longer than `LONG_RUN_S`, else None."""
    estimate = seconds_per_image * remaining
    if estimate < LONG_RUN_S:
        return None
    return (f"warning: about {format_duration(estimate)} to label {remaining} more images at {1 / seconds_per_image:.2g} "
            f"images/s on {device.type} ({config.num_homographies} teacher runs an image); fewer --num-homographies, "
            "a GPU or fewer images cut it, and a stopped run continues where it stopped")


def pick_device(name: str | None = None) -> torch.device:
    """``--device``: cpu or cuda[:N], checked against this machine; the default is cuda when there is one."""
    if not name:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise ToolkitError(f"--device {name!r}: expected cpu or cuda[:N]") from None
    if device.type not in ("cpu", "cuda"):
        raise ToolkitError(f"--device {name!r}: expected cpu or cuda[:N]")
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ToolkitError(f"--device {name}: this torch build sees no CUDA device; use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ToolkitError(f"--device {name}: only {torch.cuda.device_count()} CUDA device(s) here")
    return device


def check_config(config: AdaptationConfig) -> None:
    """Refuse settings that label nothing or cannot run, before a label folder is created."""
    height, width = config.size
    if not 1 <= config.num_homographies <= MAX_HOMOGRAPHIES:
        raise ToolkitError(f"--num-homographies must be between 1 and {MAX_HOMOGRAPHIES}, got {config.num_homographies}")
    if not 1 <= config.max_keypoints <= height * width // 4:
        raise ToolkitError(f"--max-keypoints must be between 1 and {height * width // 4} at {height}x{width}, "
                           f"got {config.max_keypoints}")
    if not 0 <= config.nms_radius < min(height, width) // 4:
        raise ToolkitError(f"--nms-radius must be between 0 and {min(height, width) // 4 - 1} at {height}x{width}, "
                           f"got {config.nms_radius}")


def _remove_new_store(out: Path, existed: bool) -> None:
    """Undo a first run that labelled nothing: its files, and the folder if this run made it."""
    for name in ("store.json", "index.json"):
        (out / name).unlink(missing_ok=True)
    shutil.rmtree(out / "items", ignore_errors=True)
    if not existed:
        shutil.rmtree(out, ignore_errors=True)


def label_folder(
    teacher_name: str,
    images: str | Path,
    out: str | Path,
    config: AdaptationConfig,
    device: torch.device | None = None,
    progress: bool = True,
) -> LabelSummary:
    """Label every readable image under ``images`` into the store at ``out`` (resumable)."""
    check_config(config)
    out = Path(out)
    with locked_output_dir(out):  # one labelling run per store at a time
        return _label_into(teacher_name, images, out, config, device, progress)


def _label_into(teacher_name: str, images: str | Path, out: Path, config: AdaptationConfig,
                device: torch.device | None, progress: bool) -> LabelSummary:
    from models.teachers import build_teacher

    files = find_images(images)
    if not files:
        raise ToolkitError(f"no image files in {images}")
    device = device or pick_device()
    teacher = build_teacher(teacher_name).to(device)
    if config.descriptor_stride and not hasattr(teacher, "dense"):
        raise ToolkitError(f"--descriptors needs a teacher with a descriptor map (alike-t|s|n|l), not {teacher_name}")
    if config.descriptor_stride and any(side % config.descriptor_stride for side in config.size):
        raise ToolkitError(f"--size sides must be multiples of {config.descriptor_stride} with --descriptors")
    existed = out.exists()
    created = not (out / "store.json").exists()
    store = LabelStore.create_or_open(out, teacher_name, config.to_dict())
    root = Path(images)
    labelled = skipped = unreadable = 0
    start = time.perf_counter()
    # a bar on a terminal, a line with the ETA every few seconds in a log (vo_runtime.progress)
    bar = progress_bar(files, desc="label", unit="img", enabled=progress)
    try:
        for path in bar:
            loaded = read_image(path, config.size)
            if loaded is None:
                unreadable += 1
                continue
            gray, sha256 = loaded
            relative = path.relative_to(root).as_posix()
            if store.has(sha256):
                store.index[relative] = sha256
                skipped += 1
                continue
            # Homographies depend on the image and the seed only, so labels do not depend on run order.
            generator = torch.Generator().manual_seed(config.seed * 1_000_003 + int(sha256[:12], 16))
            image = torch.from_numpy(gray)[None, None].to(device)
            if config.descriptor_stride:
                keypoints, scores, descriptors = label_image_with_descriptors(teacher, image, config, generator)
                store.put(sha256, relative, keypoints.numpy(), scores.numpy(), descriptors.numpy())
            else:
                keypoints, scores = label_image(teacher, image, config, generator)
                store.put(sha256, relative, keypoints.numpy(), scores.numpy())
            labelled += 1
            if labelled == ESTIMATE_AFTER:
                remaining = len(files) - labelled - skipped - unreadable
                warning = cost_warning((time.perf_counter() - start) / labelled, remaining, config, image.device)
                if warning:
                    print(warning, file=sys.stderr)
            if labelled % 25 == 0:
                store.save_index()
            bar.set_postfix(new=labelled, done_before=skipped, unreadable=unreadable)
    except BaseException:
        if created and labelled == 0:  # a store that holds nothing would refuse the corrected rerun
            bar.close()
            _remove_new_store(out, existed)
            raise
        store.save_index()
        raise
    finally:
        bar.close()
    store.save_index()
    if labelled + skipped == 0:
        if created:  # leave no empty label folder behind
            _remove_new_store(out, existed)
        raise ToolkitError(f"none of the {len(files)} image files in {images} could be read")
    return LabelSummary(labelled, skipped, unreadable, time.perf_counter() - start)


def run(args: argparse.Namespace) -> int:
    threads = min(2, available_cores()) if args.threads is None else check_thread_count(args.threads, "--threads", ToolkitError)
    config = AdaptationConfig(
        num_homographies=args.num_homographies, size=parse_size(args.size), max_keypoints=args.max_keypoints,
        nms_radius=args.nms_radius, descriptor_stride=4 if args.descriptors else 0, subpixel=args.subpixel,
    )
    device = pick_device(args.device)
    torch.set_num_threads(threads)
    summary = label_folder(args.teacher, args.images, args.out, config, device)
    print(
        f"labelled {summary.labelled} images ({summary.images_per_second:.2f} images/s), "
        f"{summary.skipped} already labelled, {summary.unreadable} unreadable skipped -> {args.out}"
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "label",
        help="label an image folder with a teacher under homographic adaptation",
        description="Run a teacher on many random homographic warps of every image, average the un-warped "
        "score maps, keep the NMS peaks: the keypoint labels `toolkit train` learns from.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--teacher", required=True,
                        help="alike-t|alike-s|alike-n|alike-l|aliked-t16|aliked-n16|superpoint:PATH|shi-tomasi (ALIKE "
                        "weights from $EDGEFEAT_ALIKE_WEIGHTS, default ../shared/data/weights_alike)")
    parser.add_argument("--images", required=True, help="folder of images (searched recursively)")
    parser.add_argument("--out", required=True, help="label folder to create or continue")
    parser.add_argument("--num-homographies", type=int, default=100, help="warps per image, identity included (default 100)")
    parser.add_argument("--size", default="240x320", help="HxW images are labelled and trained at (default 240x320)")
    parser.add_argument("--max-keypoints", type=int, default=512, help="keypoints kept per image (default 512)")
    parser.add_argument("--nms-radius", type=int, default=4, help="label NMS radius in pixels (default 4)")
    parser.add_argument(
        "--descriptors", action="store_true",
        help="also keep the teacher's dense descriptor map at 1/4 resolution (ALIKE teachers; needed by the distill recipe)",
    )
    parser.add_argument(
        "--subpixel", action="store_true",
        help="keypoints at the teacher's sub-pixel positions (5x5 soft-argmax of its score map around each peak, "
        "temperature 0.1, as ALIKE) instead of the peak pixel",
    )
    parser.add_argument(
        "--threads", type=int, default=None,
        help="CPU threads for the teacher, at most the cores (default 2, or 1 on one core; use 1 when another job "
        "shares a 2-core machine)",
    )
    parser.add_argument("--device", default=None, help="cpu or cuda[:N] (default: cuda when available)")
    parser.set_defaults(func=run)
