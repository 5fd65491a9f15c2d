"""Warped training pairs made on the fly from labelled images.

A sample is a pure function of an integer sample id: the id picks the image (a fresh permutation per
epoch) and seeds the homography and the augmentation. The trainer asks for ids ``step * world * batch
+ rank * batch + i``, so a resumed or multi-process run sees exactly the samples it would have seen.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from toolkit.errors import ToolkitError
from toolkit.training.augment import AugmentConfig, photometric_augment
from toolkit.training.homographies import (
    HomographyConfig,
    points_inside,
    sample_homography,
    valid_mask,
    warp_images,
    warp_points,
)
from toolkit.training.label_store import LabelStore, find_images, read_image

CELL = 8
DUSTBIN = 64


@dataclass
class LabelledImage:
    path: Path
    sha256: str
    keypoints: np.ndarray  # [N, 2] (x, y) at the label size
    scores: np.ndarray  # [N]
    gray: np.ndarray | None = None  # [H, W] uint8 at the label size x detail, decoded once when the run starts


def detail_size(size: tuple[int, int], detail: float) -> tuple[int, int]:
    """The (height, width) an image is kept at: the label size scaled by ``detail``, same aspect."""
    return max(1, round(size[0] * detail)), max(1, round(size[1] * detail))


def load_labelled_images(folder: str | Path, store: LabelStore, detail: float = 1.0) -> tuple[list[LabelledImage], int]:
    """Every readable image under ``folder`` with its labels; (records, number of unreadable files skipped).

    Images are kept at the label store's size times ``detail`` (same centre crop); labels stay in
    label-size pixels. A ``detail`` above 1 keeps real fine structure for views that enlarge the image.

    Raises:
        ToolkitError: no image files, none readable, or readable images without labels in ``store``.
    """
    files = find_images(folder)
    if not files:
        raise ToolkitError(f"no image files in {folder}")
    records, unreadable, unlabelled = [], 0, []
    for path in files:
        loaded = read_image(path, detail_size(store.size, detail))
        if loaded is None:
            unreadable += 1
            continue
        sha256 = loaded[1]
        if not store.has(sha256):
            unlabelled.append(path)
            continue
        keypoints, scores = store.get(sha256)
        # Kept decoded (uint8, ~77 kB at 240x320): decoding and hashing per sample cost ~5 % of a step.
        # The hash is the file's, so the labels are found whatever size the image is kept at.
        gray = np.round(loaded[0] * 255.0).astype(np.uint8)
        records.append(LabelledImage(path, sha256, keypoints, scores, gray))
    if not records and not unlabelled:
        raise ToolkitError(f"none of the {len(files)} image files in {folder} could be read")
    if unlabelled:
        raise ToolkitError(
            f"{len(unlabelled)} of {len(unlabelled) + len(records)} images in {folder} have no labels in {store.root} "
            f"(first: {unlabelled[0].name}); label them with `toolkit label` using the same settings"
        )
    return records, unreadable


def split_train_val(
    records: list[LabelledImage], val_fraction: float, val_max: int
) -> tuple[list[LabelledImage], list[LabelledImage]]:
    """Hold back images by hash (stable when files are added or renamed): at least one each side.

    Raises:
        ToolkitError: fewer than two images.
    """
    if len(records) < 2:
        raise ToolkitError("training needs at least 2 usable images (one is held back for validation)")
    ordered = sorted(records, key=lambda r: r.sha256)
    count = min(max(1, round(val_fraction * len(ordered))), val_max, len(ordered) - 1)
    return ordered[count:], ordered[:count]


def cell_labels(keypoints: torch.Tensor, scores: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """65-way class of every 8x8 cell: the position (dy*8 + dx) of its best keypoint, 64 = no keypoint.

    Args:
        keypoints: [N, 2] (x, y) pixels, inside the image.
        scores: [N] positive.
        size: (H, W) multiples of 8.
    Returns:
        [H/8, W/8] int64.
    """
    return cell_labels_and_offsets(keypoints, scores, size)[0]


def _to_cells(canvas: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """[..., H*W] -> [..., h, w, 64] with channel dy*8+dx, the pixel_shuffle order of the detector head."""
    lead = canvas.shape[:-1]
    cells = canvas.reshape(*lead, height // CELL, CELL, width // CELL, CELL).transpose(-3, -2)
    return cells.reshape(*lead, height // CELL, width // CELL, CELL * CELL)


def cell_labels_and_offsets(
    keypoints: torch.Tensor, scores: torch.Tensor, size: tuple[int, int]
) -> tuple[torch.Tensor, torch.Tensor]:
    """`cell_labels` plus where inside its labelled pixel each cell's keypoint lies.

    Returns:
        labels [H/8, W/8] int64 and offsets [2, H/8, W/8] (x, y) in [-0.5, 0.5]: the keypoint minus the centre
        of its labelled pixel (0 in cells without a keypoint).
    """
    height, width = size
    canvas = torch.zeros(height * width)
    offsets = torch.zeros(2, height * width)
    if keypoints.shape[0]:
        x = keypoints[:, 0].round().long().clamp(0, width - 1)
        y = keypoints[:, 1].round().long().clamp(0, height - 1)
        index = y * width + x
        strength = scores.float().clamp_min(1e-6)
        canvas.scatter_reduce_(0, index, strength, reduce="amax")
        winner = strength == canvas[index]  # the best keypoint of its pixel writes the offset
        within = (keypoints - torch.stack([x, y], dim=1).float()).clamp(-0.5, 0.5)
        offsets[:, index[winner]] = within[winner].T
    best, position = _to_cells(canvas, height, width).max(dim=-1)
    labels = torch.where(best > 0, position, torch.full_like(position, DUSTBIN))
    cell_offsets = _to_cells(offsets, height, width).gather(-1, position[None].expand(2, -1, -1)[..., None])[..., 0]
    return labels, cell_offsets * (best > 0)


def cell_validity(mask: torch.Tensor) -> torch.Tensor:
    """[1, H, W] pixel mask -> [H/8, W/8] bool, True where the whole cell is valid."""
    return -torch.nn.functional.max_pool2d(-mask[None], CELL)[0, 0] > 0.5


class EpochOrder:
    """Which image a sample id trains on: a fresh seeded permutation of the images per epoch."""

    def __init__(self, count: int, seed: int) -> None:
        self.count, self.seed = count, seed
        self._permutations: dict[int, torch.Tensor] = {}

    def __call__(self, sample_id: int) -> int:
        epoch, position = divmod(sample_id, self.count)
        if epoch not in self._permutations:
            generator = torch.Generator().manual_seed(self.seed * 7919 + epoch)
            self._permutations = {epoch: torch.randperm(self.count, generator=generator)}
        return int(self._permutations[epoch][position])


class WarpedPairs(Dataset):
    """Map-style dataset indexed by sample id (any non-negative int).

    Item: image_a, image_b [1, H, W]; homography [3, 3] (a -> b); labels_a, labels_b [H/8, W/8] int64;
    valid_b [H/8, W/8] bool (cells of b whose content comes from inside a).
    """

    def __init__(
        self,
        images: list[LabelledImage],
        size: tuple[int, int],
        homography: HomographyConfig,
        augment: AugmentConfig | None,
        seed: int,
    ) -> None:
        if not images:
            raise ToolkitError("no labelled images to train on")
        self.images = images
        self.size = size
        self.homography = homography
        self.augment = augment
        self.seed = seed
        self.image_index = EpochOrder(len(images), seed)

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, sample_id: int) -> dict[str, torch.Tensor]:
        record = self.images[self.image_index(sample_id)]
        if record.gray is not None:
            gray = record.gray.astype(np.float32) / 255.0
        else:
            loaded = read_image(record.path, self.size)
            if loaded is None:
                raise ToolkitError(f"image became unreadable during training: {record.path}")
            gray = loaded[0]
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + sample_id)
        height, width = self.size
        image_a = torch.from_numpy(gray)[None]
        homography = sample_homography(height, width, self.homography, generator)
        image_b = warp_images(image_a[None], homography[None])[0]
        mask_b = valid_mask(homography[None], self.size)[0]
        keypoints = torch.from_numpy(record.keypoints).float()
        scores = torch.from_numpy(record.scores).float()
        warped = warp_points(keypoints, homography)
        inside = points_inside(warped, self.size)
        if self.augment is not None:
            image_a = photometric_augment(image_a, self.augment, generator)
            image_b = photometric_augment(image_b, self.augment, generator) * mask_b
        return {
            "image_a": image_a,
            "image_b": image_b,
            "homography": homography,
            "labels_a": cell_labels(keypoints, scores, self.size),
            "labels_b": cell_labels(warped[inside], scores[inside], self.size),
            "valid_b": cell_validity(mask_b),
        }


class StepBatchSampler(Sampler[list[int]]):
    """Batches of sample ids for steps ``start_step .. total_steps - 1`` of one rank."""

    def __init__(self, start_step: int, total_steps: int, batch: int, rank: int = 0, world: int = 1) -> None:
        self.start_step, self.total_steps = start_step, total_steps
        self.batch, self.rank, self.world = batch, rank, world

    def __len__(self) -> int:
        return max(0, self.total_steps - self.start_step)

    def __iter__(self) -> Iterator[list[int]]:
        for step in range(self.start_step, self.total_steps):
            first = (step * self.world + self.rank) * self.batch
            yield list(range(first, first + self.batch))
