"""`toolkit eval synth`: HPatches-style sequences generated from any frames, deterministically.

A sequence is a reference image (1) and five targets (2..6) with the homographies ``H_1_k`` reference ->
target, all rendered at one size (`SynthConfig.out_size`, 480x640 by default; the evaluation resizes them to
``--size`` as it does HPatches images). Kinds: ``viewpoint`` (group ``v``, `synth_viewpoint`) and ``darkness``
(group ``dark``, `synth_darkness`). Each sequence is seeded from the user's seed, its kind, its source frame's
content hash and how often that frame was picked before (`synth_frames.pick_frames`), so a sequence does not
depend on the other frames, the order they were listed in or how many sequences were asked for.
"""
from __future__ import annotations

import hashlib
import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np

from toolkit.evaluation.datasets import ImagePair, load_gray
from toolkit.evaluation.synth_darkness import darkness_targets
from toolkit.evaluation.synth_frames import Frame, pick_frames
from toolkit.evaluation.synth_viewpoint import (CROP_SHARE, CaptureNoise, HomographyRanges, capture, reference_crop,
                                                render, shrink_source, viewpoint_targets)

# kind -> (index, which fixes its seeds and frame picks; name prefix, which is its HPatches group)
KINDS: dict[str, tuple[int, str]] = {"viewpoint": (0, "v"), "darkness": (1, "dark")}
TARGETS = 5
DEFAULT_SEQUENCES = 60   # per kind: 300 pairs each


@dataclass(frozen=True)
class SynthConfig:
    """What to generate: ``sequences`` per kind of ``kinds``, rendered at ``out_size`` (height, width)."""

    seed: int = 0
    sequences: int = DEFAULT_SEQUENCES
    kinds: tuple[str, ...] = ("viewpoint", "darkness")
    out_size: tuple[int, int] = (480, 640)
    ranges: HomographyRanges = field(default_factory=HomographyRanges)
    capture: CaptureNoise = field(default_factory=CaptureNoise)  # viewpoint sequences: each view its own exposure


@dataclass
class SynthSequence:
    """One generated sequence: ``images[0]`` the reference, ``images[k-1]`` target k (HxW uint8), and
    ``homographies[k-2]`` H_1_k (3x3 float64, H[2, 2] = 1)."""

    name: str
    kind: str
    source: Frame
    repeat: int
    images: list[np.ndarray]
    homographies: list[np.ndarray]

    @property
    def group(self) -> str:
        return KINDS[self.kind][1]


def sequence_seed(seed: int, kind: str, frame: Frame, repeat: int) -> np.random.SeedSequence:
    """The seed of one sequence: the user's seed, the kind, the frame's content and its repeat."""
    return np.random.SeedSequence([seed, KINDS[kind][0], repeat, int(frame.sha256[:32], 16)])


def sequence_name(kind: str, frame: Frame, repeat: int, digits: int = 8) -> str:
    """``v_<stem>_<sha8>`` or ``dark_<stem>_<sha8>`` (``_r<n>`` for a frame picked again): stable and readable."""
    stem = re.sub(r"[^A-Za-z0-9.-]+", "-", frame.path.stem).strip("-") or "frame"
    suffix = f"_r{repeat}" if repeat else ""
    return f"{KINDS[kind][1]}_{stem}_{frame.sha256[:digits]}{suffix}"


def generate_sequence(kind: str, frame: Frame, repeat: int, config: SynthConfig, name: str) -> SynthSequence:
    """One sequence of ``kind`` from ``frame`` (read as gray; `ToolkitError` if it cannot be decoded)."""
    rng = np.random.default_rng(sequence_seed(config.seed, kind, frame, repeat))
    source = load_gray(frame.path)
    shrink, to_source = reference_crop(source.shape[:2], config.out_size)
    source = shrink_source(source, shrink)
    reference = render(source, to_source, config.out_size)
    if kind == "viewpoint":
        targets = viewpoint_targets(source, to_source, config.out_size, TARGETS, rng, config.ranges)
        # drawn after the geometry, so the homographies do not depend on the noise settings
        reference = capture(reference, rng, config.capture)
        targets = [(capture(image, rng, config.capture), homography) for image, homography in targets]
    else:
        targets = darkness_targets(reference, rng)
    return SynthSequence(name, kind, frame, repeat, [reference] + [image for image, _ in targets],
                         [homography for _, homography in targets])


def _unique_names(picks: list[tuple[str, Frame, int]]) -> list[str]:
    """Names of the picks; more hash digits where two would share one (distinct frames with one stem and
    the same first digits)."""
    digits = 8
    while True:
        names = [sequence_name(kind, frame, repeat, digits) for kind, frame, repeat in picks]
        if len(set(names)) == len(names) or digits >= 64:
            return names
        digits *= 2


def plan_sequences(frames: list[Frame], config: SynthConfig) -> list[tuple[str, Frame, int]]:
    """(kind, frame, repeat) of every sequence to make, kind by kind in `KINDS` order."""
    return [(kind, frame, repeat) for kind in KINDS if kind in config.kinds
            for frame, repeat in pick_frames(frames, config.sequences, KINDS[kind][0])]


def generate_sequences(frames: list[Frame], config: SynthConfig) -> list[SynthSequence]:
    """The sequences made from ``frames`` (`synth_frames.find_frames`), in name order, as `read_hpatches`
    lists the folders `write_sequences` makes."""
    picks = plan_sequences(frames, config)
    sequences = [generate_sequence(kind, frame, repeat, config, name)
                 for (kind, frame, repeat), name in zip(picks, _unique_names(picks))]
    return sorted(sequences, key=lambda s: s.name)


def image_key(sequence: str, index: int) -> str:
    """The in-memory name of image ``index`` (1..6) of a sequence, as if it were a file of the HPatches layout."""
    return f"{sequence}/{index}.png"


def in_memory_pairs(sequences: list[SynthSequence]) -> tuple[list[ImagePair], dict[str, np.ndarray]]:
    """The pairs (1, k) of every sequence, named as `read_hpatches` names them, and the images by path."""
    pairs, images = [], {}
    for sequence in sequences:
        for index, image in enumerate(sequence.images, start=1):
            images[image_key(sequence.name, index)] = image
        for index, homography in enumerate(sequence.homographies, start=2):
            pairs.append(ImagePair(f"{sequence.name}/1-{index}", sequence.group, Path(image_key(sequence.name, 1)),
                                   Path(image_key(sequence.name, index)), homography))
    return pairs, images


def homography_text(homography: np.ndarray) -> str:
    """3 rows of 3 numbers, each written so that reading it back gives the same float64."""
    return "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in homography)


def describe(frames: list[Frame], sequences: list[SynthSequence], config: SynthConfig) -> dict[str, object]:
    """What was generated, for results.json and the written folder: settings, and each sequence's source."""
    return {"seed": config.seed, "sequences_per_kind": config.sequences, "kinds": list(config.kinds),
            "image_size": list(config.out_size), "crop_share": CROP_SHARE, "frames_found": len(frames),
            "homography_ranges": asdict(config.ranges), "capture_noise": asdict(config.capture),
            "sequences": [{"name": s.name, "kind": s.kind, "source": str(s.source.path), "source_key": s.source.key,
                           "source_sha256": s.source.sha256, "repeat": s.repeat} for s in sequences]}


SYNTH_MANIFEST = "synth.json"


def write_sequences(folder: Path, sequences: list[SynthSequence], description: dict[str, object]) -> None:
    """The HPatches layout in ``folder`` (an empty staging folder): ``<seq>/1.png..6.png``, ``<seq>/H_1_k``,
    and `SYNTH_MANIFEST` (what `describe` says). PNG is lossless, so `read_hpatches` reads the same pixels."""
    for sequence in sequences:
        target = folder / sequence.name
        target.mkdir()
        for index, image in enumerate(sequence.images, start=1):
            if not cv2.imwrite(str(target / f"{index}.png"), image):
                raise OSError(f"cannot write {target / f'{index}.png'}")
        for index, homography in enumerate(sequence.homographies, start=2):
            (target / f"H_1_{index}").write_text(homography_text(homography))
    (folder / SYNTH_MANIFEST).write_text(json.dumps(description, indent=2) + "\n")


def content_digest(sequences: list[SynthSequence]) -> str:
    """sha256 over every image's pixels and every homography's text: equal digests, equal sequences."""
    digest = hashlib.sha256()
    for sequence in sequences:
        digest.update(sequence.name.encode())
        for image in sequence.images:
            digest.update(np.ascontiguousarray(image).tobytes())
        for homography in sequence.homographies:
            digest.update(homography_text(homography).encode())
    return digest.hexdigest()
