"""Render the parity/calibration images that ship inside the package (``export/parity_images``).

Run once by a developer (``python -m export.render_parity_images``); the PNGs are committed with the
PROVENANCE.md this writes. Sources, both free of licence restrictions:

- ``grace_hopper.jpg`` from matplotlib's sample data: an official U.S. Navy photograph (public domain);
- synthetic scenes drawn here with OpenCV (polygons, ellipses, lines, checkers: ours, BSD-3-Clause).

Each comes at 240x320 in normal light and darkened with sensor noise (the deployment's dark interiors),
so export parity and INT8 calibration see both regimes without ``../shared``.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

OUT = Path(__file__).resolve().parent / "parity_images"
SIZE = (240, 320)  # height, width


def synthetic_scene(seed: int) -> np.ndarray:
    """A textured 240x320 uint8 scene of random shapes on a smooth gradient background."""
    rng = np.random.default_rng(seed)
    height, width = SIZE
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float32)
    image = 60 + 80 * (xs / width) + 40 * np.sin(ys / 37.0)
    image = image.astype(np.uint8)
    for _ in range(14):
        colour = int(rng.integers(0, 256))
        kind = rng.integers(0, 4)
        if kind == 0:
            points = rng.integers([0, 0], [width, height], size=(int(rng.integers(3, 7)), 2)).astype(np.int32)
            cv2.fillPoly(image, [cv2.convexHull(points)], colour)
        elif kind == 1:
            centre = tuple(int(v) for v in rng.integers([0, 0], [width, height]))
            axes = tuple(int(v) for v in rng.integers(8, 50, size=2))
            cv2.ellipse(image, centre, axes, float(rng.uniform(0, 180)), 0, 360, colour, -1)
        elif kind == 2:
            p, q = (tuple(int(v) for v in rng.integers([0, 0], [width, height])) for _ in range(2))
            cv2.line(image, p, q, colour, int(rng.integers(1, 5)))
        else:
            x, y = (int(v) for v in rng.integers([0, 0], [width - 60, height - 60]))
            cell = int(rng.integers(6, 14))
            for i in range(0, 60, cell):
                for j in range(0, 60, cell):
                    if (i // cell + j // cell) % 2:
                        image[y + i : y + i + cell, x + j : x + j + cell] = colour
    return cv2.GaussianBlur(image, (3, 3), 0.8)


def darkened(image: np.ndarray, seed: int) -> np.ndarray:
    """Gamma 2.2, gain 0.35, Gaussian noise sigma 2: a dim interior frame."""
    rng = np.random.default_rng(seed)
    dark = 255.0 * 0.35 * (image.astype(np.float32) / 255.0) ** 2.2 + rng.normal(0.0, 2.0, image.shape)
    return np.clip(np.rint(dark), 0, 255).astype(np.uint8)


def hopper() -> np.ndarray:
    import matplotlib.cbook

    with matplotlib.cbook.get_sample_data("grace_hopper.jpg") as file:
        data = np.frombuffer(file.read(), np.uint8)
    gray = cv2.imdecode(data, cv2.IMREAD_GRAYSCALE)  # 600x512
    crop = gray[60 : 60 + 384, :]  # 384x512: the 3:4 aspect of 240x320
    return cv2.resize(crop, (SIZE[1], SIZE[0]), interpolation=cv2.INTER_AREA)


def main() -> None:
    OUT.mkdir(exist_ok=True)
    images = {
        "hopper.png": hopper(),
        "hopper-dark.png": darkened(hopper(), 1),
        "shapes.png": synthetic_scene(7),
        "shapes-dark.png": darkened(synthetic_scene(11), 2),
    }
    for name, image in images.items():
        cv2.imwrite(str(OUT / name), image)
    (OUT / "PROVENANCE.md").write_text(
        "# Shipped parity and calibration images\n\n"
        "Rendered by `python -m export.render_parity_images` (see that module); 240x320 gray PNG.\n\n"
        "| file | source | licence |\n|---|---|---|\n"
        "| hopper.png | matplotlib sample data `grace_hopper.jpg` (Commodore Grace M. Hopper, official U.S. Navy "
        "photograph), cropped to 3:4 and resized | public domain (work of the U.S. federal government) |\n"
        "| hopper-dark.png | the same, gamma 2.2, gain 0.35, Gaussian noise sigma 2 | public domain |\n"
        "| shapes.png | synthetic scene drawn by this project (seed 7) | BSD-3-Clause (this project) |\n"
        "| shapes-dark.png | synthetic scene (seed 11), darkened as above | BSD-3-Clause (this project) |\n\n"
        "Used by `toolkit export` (parity) and `toolkit quantise` (INT8 calibration) when no image folder is given.\n"
    )


if __name__ == "__main__":
    main()
