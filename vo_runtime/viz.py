"""Pictures of the VO at work (``--viz``): each frame with its keypoints, the landmarks it tracked, and its state.

One overlay per frame (`draw_frame`): the frame contrast-stretched (a dark frame shows its structure), every
keypoint as a small grey dot, the keypoints matched to a landmark (the pose's inliers) in the state's colour,
and a banner with the frame index, the state, what tracked it and the counts. `VizWriter` puts the overlays into
``viz.mp4`` (OpenCV's writer) and keeps a PNG of every ``every``-th frame and of every frame that was not
tracked, so a failure can be looked at without scrubbing a video.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vo_runtime.config import VOResult

# BGR colours per state: tracked frames green, relocalised/reinitialised blue, lost red, the rest grey
STATE_COLOURS = {"tracking": (60, 200, 60), "relocalised": (230, 160, 40), "reinitialised": (230, 90, 200),
                 "lost": (40, 40, 230), "initialising": (0, 200, 230), "skipped": (128, 128, 128)}
TRACKED = ("tracking", "relocalised", "reinitialised")


def stretch(gray: np.ndarray) -> np.ndarray:
    """Grey levels spread from the 1st to the 99th percentile over 0..255 (uint8 in and out)."""
    low, high = np.percentile(gray, (1, 99))
    if high - low < 1:
        return gray.copy()
    return np.clip((gray.astype(np.float32) - low) * (255.0 / (high - low)), 0, 255).astype(np.uint8)


def draw_frame(gray: np.ndarray, result: VOResult, keypoints: np.ndarray | None,
               landmark: np.ndarray | None) -> np.ndarray:
    """The overlay of one frame (HxWx3 BGR uint8).

    gray: HxW uint8 frame; keypoints: [N, 2] frame pixels (None: none known); landmark: [N] landmark id per
    keypoint, -1 where none (None: the frame tracked nothing).
    """
    image = cv2.cvtColor(stretch(gray), cv2.COLOR_GRAY2BGR)
    colour = STATE_COLOURS.get(result.status, (255, 255, 255))
    if keypoints is not None and len(keypoints):
        points = np.rint(np.asarray(keypoints)).astype(np.int32)
        for x, y in points:
            cv2.circle(image, (int(x), int(y)), 1, (150, 150, 150), -1, cv2.LINE_AA)
        if landmark is not None and result.status in TRACKED:
            for x, y in points[np.asarray(landmark) >= 0]:
                cv2.circle(image, (int(x), int(y)), 3, colour, 1, cv2.LINE_8)
    if result.status not in TRACKED:  # a frame without a pose of its own: framed in its colour
        cv2.rectangle(image, (0, 0), (image.shape[1] - 1, image.shape[0] - 1), colour, 4)
    text = (f"#{result.index} {result.status}" + (f" ({result.tracked_by})" if result.tracked_by else "") +
            f"  features {result.num_features}  inliers {result.num_inliers}" + ("  keyframe" if result.keyframe else ""))
    scale = max(0.4, image.shape[1] / 1400.0)
    cv2.rectangle(image, (0, 0), (image.shape[1], int(28 * scale + 8)), (0, 0, 0), -1)
    cv2.putText(image, text, (6, int(22 * scale + 2)), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return image


class VizWriter:
    """Overlays into ``folder``: ``viz.mp4`` at ``fps`` and ``viz/NNNNNN.png`` for every ``every``-th frame and
    every frame not tracked. The video is left out (``video`` False) where OpenCV has no mp4 writer."""

    def __init__(self, folder: Path, fps: float = 10.0, every: int = 10) -> None:
        self.folder, self.fps, self.every = Path(folder), float(fps), max(1, int(every))
        (self.folder / "viz").mkdir(parents=True, exist_ok=True)
        self._video: cv2.VideoWriter | None = None
        self.video = True
        self.pngs = 0

    def add(self, overlay: np.ndarray, result: VOResult) -> None:
        if result.index % self.every == 0 or result.status not in TRACKED:
            cv2.imwrite(str(self.folder / "viz" / f"{result.index:06d}.png"), overlay)
            self.pngs += 1
        if self.video and self._video is None:
            height, width = overlay.shape[:2]
            self._video = cv2.VideoWriter(str(self.folder / "viz.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                          (width, height))
            self.video = self._video.isOpened()
        if self.video:
            self._video.write(overlay)

    def close(self) -> None:
        if self._video is not None:
            self._video.release()
        if not self.video and (self.folder / "viz.mp4").exists():
            (self.folder / "viz.mp4").unlink()  # an empty file the writer left (ours: written in the staging folder)
