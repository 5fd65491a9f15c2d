"""Warped pairs for the distill recipe: multi-scale views of each image, the teacher's keypoints and its
descriptors, all carried into the frame the student sees.

A sample starts from the image at the label store's size (the "base", where the teacher ran once):

    view a = a crop of the base, resized by a zoom z (z < 1 shrinks, z > 1 enlarges), at the step's size
    view b = view a under a random homography (``HomographyConfig``)

Keypoint labels are the teacher's keypoints mapped into each view and reduced to one per 8x8 cell
*there* (`cell_labels`), so the within-cell position a label asks for is the one at the student's own
resolution. Teacher descriptors are sampled from the stored 1/4-resolution map at each student cell's
centre mapped back into the base. The step's size cycles through ``sizes``, so one model serves small
and large inputs; a sample is a pure function of its id, as in `toolkit.training.pairs`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from toolkit.errors import ToolkitError
from toolkit.training.augment import AugmentConfig, photometric_augment
from toolkit.training.homographies import HomographyConfig, points_inside, sample_homography, warp_points
from toolkit.training.label_store import LabelStore
from toolkit.training.pairs import CELL, EpochOrder, LabelledImage, cell_labels_and_offsets, cell_validity


@dataclass
class MultiScaleConfig:
    """Sizes the student trains at (one per step, in turn) and the zoom range of view a."""

    sizes: list[list[int]] = field(default_factory=lambda: [[120, 160], [176, 232], [240, 320]])
    max_zoom: float = 1.6  # view a may enlarge the base up to this factor (finer detail per cell)
    # Images are kept at `detail` x the label size: an enlarged view then shows the photo's own fine
    # structure (and noise) instead of an interpolated blur, as a 480x640 input does.
    detail: float = 1.0

    def __post_init__(self) -> None:
        self.sizes = [[int(h), int(w)] for h, w in self.sizes]
        if not self.sizes or any(h % CELL or w % CELL or h < 2 * CELL or w < 2 * CELL for h, w in self.sizes):
            raise ValueError("distill sizes must be [height, width] pairs, multiples of 8, at least 16")
        if not 0.1 <= float(self.max_zoom) <= 8.0:
            raise ValueError("max_zoom must be within [0.1, 8]")
        if not 1.0 <= float(self.detail) <= 4.0:
            raise ValueError("detail must be within [1, 4]")


def crop_zoom_homography(base: tuple[int, int], size: tuple[int, int], zoom: float, top: float, left: float) -> torch.Tensor:
    """[3, 3] base pixel -> view pixel for a crop at (top, left) of the base, resized by ``zoom``.

    Pixel centres are integers on both sides, so x_view = zoom * (x_base - left + 0.5) - 0.5.
    """
    shift = 0.5 * zoom - 0.5
    return torch.tensor(
        [[zoom, 0.0, -zoom * left + shift], [0.0, zoom, -zoom * top + shift], [0.0, 0.0, 1.0]], dtype=torch.float64
    ).float()


def detail_to_base(detail_shape: tuple[int, int], base: tuple[int, int]) -> torch.Tensor:
    """[3, 3] pixel of the image kept at detail size -> base pixel (integer pixel centres on both sides)."""
    sy, sx = base[0] / detail_shape[0], base[1] / detail_shape[1]
    return torch.tensor([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]], dtype=torch.float64)


def render_view(base: np.ndarray, homography: torch.Tensor, size: tuple[int, int], zoom: float) -> np.ndarray:
    """Warp the image [Hb, Wb] uint8 into a view of ``size`` (``homography``: image pixel -> view pixel,
    ``zoom``: view pixels per image pixel); blurred first when the view shrinks it."""
    if zoom < 0.9:  # anti-aliasing: a Gaussian as wide as the shrink factor asks for
        sigma = 0.5 * math.sqrt(1.0 / (zoom * zoom) - 1.0)
        base = cv2.GaussianBlur(base, (0, 0), sigma)
    height, width = size
    view = cv2.warpPerspective(
        base.astype(np.float32) / 255.0, homography.double().numpy(), (width, height),
        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0,
    )
    return view


def sample_map(descriptors: torch.Tensor, points: torch.Tensor, stride: int = CELL) -> torch.Tensor:
    """Bilinear sample of a map at 1/stride resolution at pixel points (centres at integers on both).

    descriptors [D, h, w], points [N, 2] (x, y) -> [N, D], unit L2 norm; points beyond the outer map
    centres read zero-padded values (they are masked out by the callers).
    """
    _, height, width = descriptors.shape
    u = (points[:, 0] + 0.5) / stride - 0.5
    v = (points[:, 1] + 0.5) / stride - 0.5
    grid = torch.stack([u * 2.0 / max(width - 1, 1) - 1.0, v * 2.0 / max(height - 1, 1) - 1.0], dim=-1)
    sampled = F.grid_sample(descriptors[None].float(), grid.view(1, 1, -1, 2), mode="bilinear", align_corners=True)
    return F.normalize(sampled[0, :, 0].transpose(0, 1), p=2.0, dim=1)


def sample_teacher(descriptors: torch.Tensor, stride: int, cells_to_base: torch.Tensor, base: tuple[int, int],
                   size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The teacher's descriptor at every student cell centre of a view.

    Args:
        descriptors: [D, Hb/stride, Wb/stride] teacher map of the base image.
        cells_to_base: [3, 3] view pixel -> base pixel.
        size: the view's (H, W).
    Returns:
        descriptors [D, H/8, W/8] (unit norm), valid [H/8, W/8] bool (centre inside the base).
    """
    height, width = size[0] // CELL, size[1] // CELL
    ys, xs = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    centres = torch.stack([xs, ys], dim=-1).reshape(-1, 2) * CELL + (CELL - 1) / 2
    in_base = warp_points(centres, cells_to_base)
    valid = points_inside(in_base, base, border=2)
    sampled = sample_map(descriptors, in_base, stride).transpose(0, 1).reshape(-1, height, width)
    return sampled, valid.reshape(height, width)


class DistillPairs(Dataset):
    """Map-style dataset indexed by sample id; ``ids_per_step`` ids share one size (one batch).

    Item: image_a, image_b [1, H, W]; homography [3, 3] (a -> b); labels_a, labels_b [H/8, W/8] int64;
    valid_b [H/8, W/8] bool; teacher_a, teacher_b [D, H/8, W/8]; teacher_valid_a, teacher_valid_b bool.
    """

    def __init__(
        self,
        images: list[LabelledImage],
        store: LabelStore,
        scales: MultiScaleConfig,
        homography: HomographyConfig,
        augment: AugmentConfig | None,
        seed: int,
        ids_per_step: int,
        fixed_size: tuple[int, int] | None = None,
    ) -> None:
        if not images:
            raise ToolkitError("no labelled images to train on")
        if not store.descriptor_stride:
            raise ToolkitError(
                f"the distill recipe (the default) needs teacher descriptors: {store.root} was labelled without "
                "--descriptors; label with an ALIKE teacher and --descriptors (toolkit label --teacher alike-n "
                "--descriptors ...), or train the paper recipe on these labels (--config with recipe = \"paper\")"
            )
        self.images, self.store, self.scales = images, store, scales
        self.homography, self.augment, self.seed = homography, augment, seed
        self.ids_per_step, self.fixed_size = ids_per_step, fixed_size
        self.image_index = EpochOrder(len(images), seed)

    def __len__(self) -> int:
        return len(self.images)

    def size_of(self, sample_id: int) -> tuple[int, int]:
        if self.fixed_size is not None:
            return self.fixed_size
        height, width = self.scales.sizes[(sample_id // self.ids_per_step) % len(self.scales.sizes)]
        return height, width

    def __getitem__(self, sample_id: int) -> dict[str, torch.Tensor]:
        record = self.images[self.image_index(sample_id)]
        if record.gray is None:
            raise ToolkitError(f"image {record.path} was not decoded")
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + sample_id)
        base = tuple(self.store.size)  # labels and teacher maps live in these pixels
        detail = detail_to_base(record.gray.shape, base)  # the kept image may be finer than the base
        size = self.size_of(sample_id)
        u = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
        min_zoom = max(size[0] / base[0], size[1] / base[1])  # the whole base fits in the view
        max_zoom = max(min_zoom, self.scales.max_zoom if self.fixed_size is None else min_zoom)
        zoom = math.exp(math.log(min_zoom) + (math.log(max_zoom) - math.log(min_zoom)) * u[0])
        top = (base[0] - size[0] / zoom) * u[1]
        left = (base[1] - size[1] / zoom) * u[2]
        base_to_a = crop_zoom_homography(base, size, zoom, top, left)
        a_to_b = sample_homography(size[0], size[1], self.homography, generator)
        base_to_b = (a_to_b.double() @ base_to_a.double()).float()
        view_zoom = zoom * float(detail[0, 0])  # view pixels per pixel of the kept image
        image_a = torch.from_numpy(render_view(record.gray, (base_to_a.double() @ detail).float(), size, view_zoom))[None]
        image_b = torch.from_numpy(render_view(record.gray, (base_to_b.double() @ detail).float(), size, view_zoom))[None]
        ones = np.full(base, 255, np.uint8)
        mask_b = torch.from_numpy(render_view(ones, base_to_b, size, 1.0) > 0.999).float()[None]

        keypoints = torch.from_numpy(record.keypoints).float()
        scores = torch.from_numpy(record.scores).float()
        in_a, in_b = warp_points(keypoints, base_to_a), warp_points(keypoints, base_to_b)
        inside_a, inside_b = points_inside(in_a, size), points_inside(in_b, size)
        teacher = torch.from_numpy(self.store.get_descriptors(record.sha256))
        stride = self.store.descriptor_stride
        teacher_a, teacher_valid_a = sample_teacher(teacher, stride, torch.linalg.inv(base_to_a.double()).float(), base, size)
        teacher_b, teacher_valid_b = sample_teacher(teacher, stride, torch.linalg.inv(base_to_b.double()).float(), base, size)
        if self.augment is not None:
            image_a = photometric_augment(image_a, self.augment, generator)
            image_b = photometric_augment(image_b, self.augment, generator) * mask_b
        valid_b = cell_validity(mask_b)
        labels_a, offsets_a = cell_labels_and_offsets(in_a[inside_a], scores[inside_a], size)
        labels_b, offsets_b = cell_labels_and_offsets(in_b[inside_b], scores[inside_b], size)
        return {
            "image_a": image_a,
            "image_b": image_b,
            "homography": a_to_b,
            "labels_a": labels_a,
            "labels_b": labels_b,
            "offsets_a": offsets_a,
            "offsets_b": offsets_b,
            "valid_b": valid_b,
            "teacher_a": teacher_a,
            "teacher_b": teacher_b,
            "teacher_valid_a": teacher_valid_a,
            "teacher_valid_b": teacher_valid_b & valid_b,
        }
