"""Training throughput: the first version's CPU step against today's, measured side by side in one run.

    before: paper recipe (CE + hinge), gather deformable sampler, float32, every sample re-read, decoded
            and SHA-256-hashed from disk (as `toolkit.training.pairs` did)
    after:  distill recipe (CE + teacher descriptors + InfoNCE), grid_sample sampler, bfloat16 autocast where the
            CPU computes bfloat16 natively (float32 elsewhere, as `toolkit train` does), images decoded once

Both train FeatureNet (default config) at the same size and batch on real photos labelled here by
alike-n (keypoints and descriptors, ~1 s). Steps alternate between the two in rounds, so machine noise
hits both alike; the script prints median pairs/s and the ratio.

    python bench/bench_train.py                       # 120x160, batch 8, 1 thread
    python bench/bench_train.py --size 240x320 --threads 2
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from export.parity import shared_data_dir  # noqa: E402
from models.deform import set_deform_strategy  # noqa: E402
from models.featurenet import FeatureNet  # noqa: E402
from toolkit.cmd_label import label_folder  # noqa: E402
from toolkit.sizes import parse_size  # noqa: E402
from toolkit.training.adaptation import AdaptationConfig  # noqa: E402
from toolkit.training.augment import AugmentConfig  # noqa: E402
from toolkit.training.cpu_precision import cpu_computes_bf16  # noqa: E402
from toolkit.training.distill_losses import DescriptorProjection, DistillLossConfig, distill_loss  # noqa: E402
from toolkit.training.distill_pairs import DistillPairs, MultiScaleConfig  # noqa: E402
from toolkit.training.homographies import HomographyConfig  # noqa: E402
from toolkit.training.label_store import LabelStore  # noqa: E402
from toolkit.training.losses import LossConfig, superpoint_loss  # noqa: E402
from toolkit.training.pairs import WarpedPairs, load_labelled_images  # noqa: E402


class Variant:
    """One training step recipe: its data, model, loss and precision."""

    def __init__(self, name: str, dataset, loss, sampler: str, bf16: bool, batch: int) -> None:
        torch.manual_seed(0)
        self.name, self.dataset, self.batch = name, dataset, batch
        self.model = set_deform_strategy(FeatureNet(), sampler).train()
        self.projection = DescriptorProjection(256, 128)
        self.optimizer = torch.optim.Adam([*self.model.parameters(), *self.projection.parameters()], lr=1e-4)
        self.loss, self.bf16, self.next_id = loss, bf16, 0

    def step(self) -> float:
        """One optimisation step from sample loading to optimizer.step(); returns its seconds."""
        start = time.perf_counter()
        items = [self.dataset[self.next_id + i] for i in range(self.batch)]
        self.next_id += self.batch
        batch = {key: torch.stack([item[key] for item in items]) for key in items[0]}
        context = torch.autocast("cpu", dtype=torch.bfloat16) if self.bf16 else contextlib.nullcontext()
        with context:
            outputs = self.model(torch.cat([batch["image_a"], batch["image_b"]]))
            count = self.batch
            a = {k: v[:count] for k, v in outputs.items()}
            b = {k: v[count:] for k, v in outputs.items()}
            losses = self.loss(a, b, batch, self.projection)
        self.optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        self.optimizer.step()
        return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="120x160", help="training size HxW (default 120x160)")
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--rounds", type=int, default=12, help="timed steps per variant (default 12)")
    parser.add_argument("--images", type=int, default=24, help="photos to label and train on (default 24)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    size = parse_size(args.size)
    data = shared_data_dir()
    if data is None:
        sys.exit("error: ../shared/data not found (the benchmark trains on real photos)")
    with tempfile.TemporaryDirectory() as tmp:
        images = Path(tmp) / "images"
        images.mkdir()
        for source in sorted((data / "train_images" / "coco128").glob("*.jpg"))[: args.images]:
            (images / source.name).symlink_to(source)
        config = AdaptationConfig(num_homographies=1, size=size, max_keypoints=1024, nms_radius=2, descriptor_stride=4)
        label_folder("alike-n", images, Path(tmp) / "labels", config, torch.device("cpu"), progress=False)
        store = LabelStore.open(Path(tmp) / "labels")
        records, _ = load_labelled_images(images, store)
        on_disk = [replace(r, gray=None) for r in records]  # the old pairs re-read every image per sample

        augment = AugmentConfig()
        before = Variant(
            "before: paper, gather, fp32, decode per sample",
            WarpedPairs(on_disk, size, HomographyConfig(), augment, 0),
            lambda a, b, batch, _p: superpoint_loss(a, b, batch, LossConfig()),
            "torch", False, args.batch,
        )
        scales = MultiScaleConfig(sizes=[list(size)])
        bf16 = cpu_computes_bf16()  # as the trainer decides
        after = Variant(
            f"after: distill, grid_sample, {'bf16' if bf16 else 'fp32 (no native bf16)'}, decoded once",
            DistillPairs(records, store, scales, HomographyConfig(), augment, 0, args.batch),
            lambda a, b, batch, p: distill_loss(a, b, batch, p, DistillLossConfig()),
            "grid_sample", bf16, args.batch,
        )
        variants = [before, after]
        for variant in variants:  # warm-up: allocator, oneDNN kernels
            variant.step()
            variant.step()
        times: dict[str, list[float]] = {v.name: [] for v in variants}
        for _ in range(args.rounds):
            for variant in variants:
                times[variant.name].append(variant.step())
    print(f"training step, FeatureNet, {size[0]}x{size[1]}, batch {args.batch}, {args.threads} thread(s), "
          f"{args.rounds} interleaved steps each, torch {torch.__version__}")
    print(f"| step | median s/step | pairs/s | x before |\n|---|---:|---:|---:|")
    base = statistics.median(times[before.name])
    for name, values in times.items():
        median = statistics.median(values)
        print(f"| {name} | {median:.3f} | {args.batch / median:.1f} | {base / median:.2f}x |")


if __name__ == "__main__":
    main()
