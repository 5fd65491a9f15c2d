"""The bad-input matrix for what used to hang or end as an internal error (issue 29, D10-D19, D23, D24): thread
counts beyond the machine, NaN weights, absurd widths, non-UTF-8 and deeply nested files, bad profile values,
NaN ground truth, truncated labels, paths of the wrong kind, and library noise beside the error line."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest
import torch

import toolkit.cli
from bad_inputs_support import KITTI_06, PAIRS, SHARED_DATA, Space, assert_refused
from test_bad_inputs_results import profile_with
from vo_runtime.machine import available_cores

TOO_MANY = str(available_cores() + 1)
NOT_UTF8 = b"\xff\xfe\x00 not text \x80\x81"


def nan_checkpoint(space: Space) -> Path:
    from models.checkpoint import load_checkpoint, save_checkpoint

    net, _ = load_checkpoint(space.assets.checkpoint)
    with torch.no_grad():
        next(net.parameters()).view(-1)[0] = float("nan")
    return save_checkpoint(net, space.root / "nan.safetensors")


def huge_width_checkpoint(space: Space) -> Path:
    """A checkpoint whose header claims a network of 10^6 channels (its tensors never load that far)."""
    from safetensors.torch import save_file

    from models.checkpoint import CHECKPOINT_FORMAT

    path = space.root / "huge.safetensors"
    header = {"format": CHECKPOINT_FORMAT, "arch": "featurenet", "metadata": "{}",
              "config": json.dumps({"widths": [16, 32, 64, 1_000_000]})}
    save_file({"w": torch.zeros(1)}, str(path), metadata=header)
    return path


def deep_json(levels: int = 100_000) -> bytes:
    return ("[" * levels + "]" * levels).encode()


def deep_toml(space: Space) -> Path:
    return space.file("deep.toml", b"x = " + b"[" * 50_000 + b"]" * 50_000 + b"\n")


def tum_copy_with_nan_pose(space: Space) -> Path:
    source = SHARED_DATA / "tum_fr2_desk_snippet"
    root = space.root / "rgbd_dataset_freiburg2_desk"
    (root / "rgb").mkdir(parents=True)
    for path in sorted((source / "rgb").iterdir())[:3]:
        shutil.copy(path, root / "rgb" / path.name)
    lines = (source / "groundtruth.txt").read_text().splitlines()
    body = [line for line in lines if line and not line.startswith("#")]
    body[5] = " ".join(body[5].split()[:1] + ["nan"] * 7)
    (root / "groundtruth.txt").write_text("\n".join(body) + "\n")
    return root


def kitti_without_calib(space: Space) -> Path:
    root = space.sequence()
    (root / "calib.txt").unlink()
    return root


def truncated_labels(space: Space) -> Path:
    labels = space.root / "labels"
    assert toolkit.cli.main(["label", "--teacher", "shi-tomasi", "--images", str(PAIRS / "low"), "--size", "64x96",
                             "--num-homographies", "1", "--out", str(labels)]) == 0
    item = sorted((labels / "items").iterdir())[0]
    item.write_bytes(item.read_bytes()[:100])
    return labels


def orb(space: Space, *extra) -> list:
    return ["vo", "--features", "orb", "--images", space.sequence(), "--no-progress", *extra]


def small_train(space: Space, labels: Path, *extra) -> list:
    config = space.file("small.json", json.dumps({"recipe": "paper", "device": "cpu", "steps": 1, "batch": 2,
                                                  "model": {"widths": [8, 16, 32, 32], "blocks": [0, 1, 1, 1],
                                                            "head_channels": 32, "descriptor_dim": 64}}).encode())
    return ["train", "--images", PAIRS / "low", "--labels", labels, "--config", config, "--out", space.root / "run",
            *extra]


def export(space: Space, *extra) -> list:
    return ["export", "--target", "x86-cpu", "--input-size", "64x64", "-o", space.root / "o", *extra]


CASES: list[tuple[str, str, Callable[[Space], list]]] = [
    # D10: thread counts bounded by the cores
    ("vo-threads-beyond-cores", "CPU core", lambda s: orb(s, "--threads", TOO_MANY)),
    ("vo-blas-threads-beyond-cores", "CPU core", lambda s: orb(s, "--blas-threads", "100000")),
    ("profile-threads-beyond-cores", "CPU core",
     lambda s: ["profile", "--model", s.assets.checkpoint, "--no-compare", "--threads", "100000"]),
    ("label-threads-beyond-cores", "CPU core",
     lambda s: ["label", "--teacher", "shi-tomasi", "--images", PAIRS / "low", "--out", s.root / "l", "--threads",
                "100000"]),
    ("train-threads-beyond-cores", "CPU core",
     lambda s: ["train", "--images", PAIRS / "low", "--labels", s.root / "l", "--threads", "100000",
                "--out", s.root / "run"]),
    # D12: NaN weights
    ("export-nan-weights", "NaN or infinite weights", lambda s: export(s, "--checkpoint", nan_checkpoint(s))),
    ("eval-nan-weights", "NaN or infinite weights",
     lambda s: ["eval", "pairs", "--data", PAIRS, "--model", nan_checkpoint(s)]),
    ("profile-nan-weights", "NaN or infinite weights",
     lambda s: ["profile", "--model", nan_checkpoint(s), "--no-compare", "--input-size", "64x64"]),
    # D13: widths no memory holds
    ("export-huge-widths", "at most 4096", lambda s: export(s, "--checkpoint", huge_width_checkpoint(s))),
    ("train-huge-widths", "at most 4096",
     lambda s: ["train", "--images", PAIRS / "low", "--labels", s.root / "l", "--out", s.root / "run",
                "--config", s.file("c.json", b'{"model": {"widths": [16, 32, 64, 1000000]}}')]),
    # D14: files that are not UTF-8
    ("profile-not-utf8", "not UTF-8", lambda s: ["profile", "--target", s.file("p.toml", NOT_UTF8)]),
    ("train-config-not-utf8", "not UTF-8",
     lambda s: ["train", "--images", PAIRS / "low", "--labels", s.root / "l", "--out", s.root / "run",
                "--config", s.file("c.json", NOT_UTF8)]),
    ("vo-calib-not-utf8", "not UTF-8",
     lambda s: ["vo", "--features", "orb", "--images", s.images("frames", 3, 64), "--calib", s.file("c.json", NOT_UTF8)]),
    # D15: profile values no target has
    ("profile-opset-huge", "max_opset must be", lambda s: ["profile", "--target", profile_with(s, "max_opset", "1000")]),
    ("profile-opset-text", "max_opset must be",
     lambda s: ["profile", "--target", profile_with(s, "max_opset", '"nineteen"')]),
    ("profile-opset-negative", "max_opset must be", lambda s: ["profile", "--target", profile_with(s, "max_opset", "-3")]),
    ("export-opset-huge", "max_opset must be",
     lambda s: export(s, "--checkpoint", s.assets.checkpoint, "--target", profile_with(s, "max_opset", "1000"))),
    ("profile-keypoints-inf", "default_max_keypoints must be",
     lambda s: ["profile", "--target", profile_with(s, "default_max_keypoints", "inf")]),
    ("profile-peak-zero", "positive finite number",
     lambda s: ["profile", "--target", profile_with(s, "peak_gflops_fp32", "0"), "--input-size", "32x48"]),
    ("profile-peak-text", "positive finite number",
     lambda s: ["profile", "--target", profile_with(s, "peak_gflops_fp32", '"fast"'), "--input-size", "32x48"]),
    ("profile-precisions-text", "precisions must be",
     lambda s: ["profile", "--target", profile_with(s, "precisions", '"fp32"')]),
    ("profile-input-size-text", "default_input_size must be",
     lambda s: ["profile", "--target", profile_with(s, "default_input_size", '"240x320"')]),
    # D16: nesting deeper than any real file
    ("profile-deep-toml", "nests", lambda s: ["profile", "--target", deep_toml(s)]),
    ("train-config-deep-json", "nests",
     lambda s: ["train", "--images", PAIRS / "low", "--labels", s.root / "l", "--out", s.root / "run",
                "--config", s.file("c.json", deep_json())]),
    ("vo-calib-deep-json", "not valid JSON",
     lambda s: ["vo", "--features", "orb", "--images", s.images("frames", 3, 64),
                "--calib", s.file("c.json", b'{"fx": ' + deep_json() + b"}")]),
    ("vo-manifest-deep-json", "not valid JSON",
     lambda s: ["vo", "--artefact", s.file("art/manifest.json", deep_json()).parent, "--images", s.sequence()]),
    # D18: ground truth with NaN poses, refused before the run
    ("vo-tum-groundtruth-nan", "non-finite poses",
     lambda s: ["vo", "--features", "orb", "--images", tum_copy_with_nan_pose(s), "--gt", "auto", "--no-progress"]),
    # D19: a truncated label file counts as missing (named, with what to do), not a BadZipFile
    ("train-truncated-labels", "have no labels", lambda s: small_train(s, truncated_labels(s))),
    # D23: messages that named the wrong thing
    ("vo-kitti-without-calib", "has image_0/ but no calib.txt", lambda s: orb_on(kitti_without_calib(s))),
    ("export-checkpoint-is-a-folder", "is a folder", lambda s: export(s, "--checkpoint", s.thesis())),
    ("vo-images-is-a-file", "is a file, not a sequence folder",
     lambda s: ["vo", "--features", "orb", "--images", s.file("x.png", b"x")]),
    ("vo-calib-is-a-folder", "is a folder",
     lambda s: ["vo", "--features", "orb", "--images", s.images("frames", 3, 64), "--calib", s.thesis()]),
    ("vo-gt-is-a-folder", "is a folder", lambda s: orb(s, "--gt", s.thesis())),
    ("vo-artefact-is-a-file", "is a file, not an artefact directory",
     lambda s: ["vo", "--artefact", s.file("art.onnx", b"x"), "--images", s.sequence()]),
    ("profile-target-is-a-folder", "is not a file",
     lambda s: ["profile", "--target", s.file("dir.toml/inside", b"").parent]),
    ("calib-json-array", "holds a JSON list",
     lambda s: ["vo", "--features", "orb", "--images", s.images("frames", 3, 64), "--calib", s.file("c.json", b"[1, 2]")]),
]


def orb_on(sequence: Path) -> list:
    return ["vo", "--features", "orb", "--images", sequence, "--no-progress"]


@pytest.mark.parametrize("name, fragment, build", CASES, ids=[case[0] for case in CASES])
def test_internal_row_is_one_error_line_and_changes_nothing(name, fragment, build, bad_input_assets, tmp_path,
                                                             capsys):
    argv = build(Space(tmp_path, bad_input_assets))
    assert_refused(toolkit.cli.main, argv, capsys, fragment, tmp_path, bad_input_assets.root)


def test_a_kitti_folder_without_calib_runs_with_calib(tmp_path, capsys):
    """D23: --calib stands in for a missing calib.txt (it said 'holds no images')."""
    root = kitti_without_calib(Space(tmp_path, None))
    assert toolkit.cli.main([str(arg) for arg in orb_on(root)] + ["--calib", str(KITTI_06 / "calib.txt")]) == 0


def test_a_resumed_label_run_relabels_a_truncated_item(tmp_path, capsys):
    """D19: a label cut short is labelled again on resume, and training then reads every label."""
    space = Space(tmp_path, None)
    labels = truncated_labels(space)
    capsys.readouterr()
    assert toolkit.cli.main(["label", "--teacher", "shi-tomasi", "--images", str(PAIRS / "low"), "--size", "64x96",
                             "--num-homographies", "1", "--out", str(labels)]) == 0
    assert "labelled 1 images" in capsys.readouterr().out
    assert toolkit.cli.main([str(arg) for arg in small_train(space, labels, "--threads", "1")]) == 0


def broken_png(path: Path) -> Path:
    """A PNG whose image data fails its checksum: libpng prints its own line while decoding it."""
    ok, encoded = cv2.imencode(".png", np.random.default_rng(0).integers(0, 255, (64, 64), np.uint8))
    data = bytearray(encoded.tobytes())
    data[60] ^= 0xFF
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(bytes(data))
    return path


def test_no_library_line_beside_the_error(tmp_path):
    """D24: libpng's own stderr line is caught (and quoted in ours); the process writes one line in all."""
    for index in range(2):
        broken_png(tmp_path / "frames" / f"{index:06d}.png")
    result = subprocess.run([sys.executable, "-m", "vo_runtime", "--features", "orb", "--images",
                             str(tmp_path / "frames"), "--calib", str(KITTI_06 / "calib.txt")],
                            capture_output=True, text=True, timeout=120, cwd=Path(__file__).resolve().parents[1])
    lines = result.stderr.splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    assert "libpng" in lines[0]  # quoted inside our line, not printed beside it


def test_python_warnings_stay_off_a_failing_command(monkeypatch, capsys):
    """D24: a library warning raised on the way to a refusal does not print above the error line."""
    import warnings

    import toolkit.cmd_export as cmd_export
    from toolkit.errors import ToolkitError

    def warns_then_fails(_args):
        warnings.warn("invalid value encountered in divide", RuntimeWarning)
        raise ToolkitError("the input is bad")

    monkeypatch.setattr(cmd_export, "run", warns_then_fails)
    assert toolkit.cli.main(["export", "--target", "x86-cpu", "-o", "unused"]) == 2
    assert capsys.readouterr().err == "error: the input is bad\n"


def test_an_allocation_failure_is_the_memory_line(monkeypatch, capsys):
    """D13: torch says an allocation failed with a RuntimeError, which missed the out-of-memory handler."""
    import toolkit.cmd_export as cmd_export

    def cannot_allocate(_args):
        raise RuntimeError("[enforce fail at alloc_cpu.cpp:117] DefaultCPUAllocator: can't allocate memory: you tried "
                           "to allocate 4000000000000 bytes")

    monkeypatch.setattr(cmd_export, "run", cannot_allocate)
    assert toolkit.cli.main(["export", "--target", "x86-cpu", "-o", "unused"]) == 2
    assert capsys.readouterr().err.startswith("error: out of memory")
