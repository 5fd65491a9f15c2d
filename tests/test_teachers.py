"""Teachers: ALIKE/ALIKED re-implementations load every published tensor and give repeatable peaks;
the superpoint:PATH loader and the Shi-Tomasi fallback; bad teacher names and files."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from models.keypoints import heatmap_from_logits, max_pool_nms
from models.superpoint import SuperPointNet
from models.teachers import build_teacher
from models.teachers.alike import ALIKE_CONFIGS
from models.teachers.aliked import ALIKED_CONFIGS
from models.errors import TeacherError
from toolkit.training.homographies import points_inside, valid_mask, warp_images, warp_points

torch.set_num_threads(1)
ALL_ALIKE = [*ALIKE_CONFIGS, *ALIKED_CONFIGS]


def real_image(shared_data: Path, size: tuple[int, int] = (120, 160)) -> torch.Tensor:
    path = sorted((shared_data / "train_images" / "coco128").glob("*.jpg"))[3]
    gray = cv2.resize(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), (size[1], size[0]), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(gray.astype(np.float32) / 255.0)[None, None]


def peaks(scores: torch.Tensor, k: int, border: int = 4) -> torch.Tensor:
    """[1, 1, H, W] -> the k strongest NMS peaks (x, y), [k, 2]."""
    suppressed = max_pool_nms(scores.clone(), 3)[0, 0]
    suppressed[:border] = suppressed[-border:] = 0
    suppressed[:, :border] = suppressed[:, -border:] = 0
    index = suppressed.reshape(-1).topk(k).indices
    width = scores.shape[-1]
    return torch.stack([index % width, index // width], 1).float()


def repeatability(teacher, image: torch.Tensor, k: int = 100) -> float:
    """Fraction of the peaks of ``image`` found again within 3 px on a known warp of it."""
    height, width = image.shape[-2:]
    angle = np.deg2rad(10.0)
    homography = torch.tensor(
        [[0.95 * np.cos(angle), -0.95 * np.sin(angle), 12.0], [0.95 * np.sin(angle), 0.95 * np.cos(angle), -4.0], [1e-4, 0, 1]],
        dtype=torch.float32,
    )[None]
    warped = warp_images(image, homography)
    with torch.no_grad():
        scores, scores_warped = teacher(image), teacher(warped)
    scores_warped = scores_warped * valid_mask(homography, (height, width), erode=4)
    moved = warp_points(peaks(scores, k), homography[0])
    seen = points_inside(moved, (height, width), border=4)
    distance = torch.cdist(moved[seen], peaks(scores_warped, k)).min(dim=1).values
    return float((distance <= 3.0).float().mean())


@pytest.mark.parametrize("name", ALL_ALIKE)
def test_alike_family_matches_every_published_tensor(name: str, shared_data: Path) -> None:
    published = torch.load(shared_data / "weights_alike" / f"{name}.pth", map_location="cpu", weights_only=True)
    teacher = build_teacher(name, shared_data / "weights_alike")
    ours = teacher.state_dict()
    # All keys matched: nothing missing, nothing unexpected, every shape and value identical.
    assert set(ours) == set(published)
    for key, tensor in published.items():
        assert ours[key].shape == tensor.shape, key
        assert torch.equal(ours[key], tensor), key
    with torch.no_grad():
        scores = teacher(real_image(shared_data, (64, 96)))
    assert scores.shape == (1, 1, 64, 96)
    assert float(scores.min()) >= 0.0 and float(scores.max()) <= 1.0
    assert float(scores.max()) > 0.5  # a real photo has confident keypoints


@pytest.mark.parametrize("name", ["alike-t", "aliked-t16"])
def test_alike_peaks_repeat_under_a_known_homography(name: str, shared_data: Path) -> None:
    teacher = build_teacher(name, shared_data / "weights_alike")
    image = real_image(shared_data)
    learned = repeatability(teacher, image)
    torch.manual_seed(0)
    chance = repeatability(lambda x: torch.rand_like(x[:, :1]), image)
    assert learned > 0.5
    assert learned > chance + 0.3


def test_superpoint_teacher_loads_a_magic_leap_layout_state_dict(tmp_path: Path) -> None:
    torch.manual_seed(0)
    network = SuperPointNet().eval()
    state = network.state_dict()
    assert {k.split(".")[0] for k in state} == {
        "conv1a", "conv1b", "conv2a", "conv2b", "conv3a", "conv3b", "conv4a", "conv4b", "convPa", "convPb", "convDa", "convDb"
    }
    path = tmp_path / "superpoint_v1.pth"
    torch.save(state, path)
    teacher = build_teacher(f"superpoint:{path}")
    image = torch.rand(1, 1, 64, 96)
    with torch.no_grad():
        expected = heatmap_from_logits(network(image)["logits"])
        assert torch.allclose(teacher(image), expected, atol=1e-6)
        assert teacher(image[..., :60, :90]).shape == (1, 1, 60, 90)  # padded to multiples of 8 and cropped


def test_shi_tomasi_peaks_on_the_corners_of_a_square() -> None:
    image = torch.zeros(1, 1, 64, 96)
    image[..., 20:44, 30:70] = 1.0
    scores = build_teacher("shi-tomasi")(image)
    assert scores.shape == image.shape and float(scores.max()) > 0.9
    found = peaks(scores, 4)
    corners = torch.tensor([[30.0, 20.0], [69.0, 20.0], [30.0, 43.0], [69.0, 43.0]])
    assert float(torch.cdist(corners, found).min(dim=1).values.max()) <= 2.0
    assert float(scores[0, 0, 5:15, 5:25].max()) < 1e-3  # flat background scores nothing


def test_bad_teacher_names_and_files_are_clear_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(TeacherError, match="unknown teacher"):
        build_teacher("sift")
    with pytest.raises(TeacherError, match="not found"):
        build_teacher(f"superpoint:{tmp_path / 'missing.pth'}")
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(TeacherError, match="cannot load"):
        build_teacher(f"superpoint:{garbage}")
    wrong = tmp_path / "wrong.pth"
    torch.save({"conv1a.weight": torch.zeros(3)}, wrong)
    with pytest.raises(TeacherError, match="cannot load"):
        build_teacher(f"superpoint:{wrong}")
    monkeypatch.setenv("EDGEFEAT_ALIKE_WEIGHTS", str(tmp_path))
    with pytest.raises(TeacherError, match="weight file not found"):
        build_teacher("alike-n")
