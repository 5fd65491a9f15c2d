"""The bad-input matrix for silent wrong results (issue 29, D5-D9, D17, D23, D25, D26): an artefact whose graph
breaks its manifest's promise, bad timestamps, NaN hardware figures, pairs the identity cannot register, and
API calls with the wrong types. Command lines: exit 2, one ``error:`` line naming the input, nothing changed.
API: a typed `VORuntimeError` and nothing changed."""
from __future__ import annotations

import threading
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

import toolkit.cli
from bad_inputs_support import PAIRS, Space, assert_refused
from fake_graphs import constant_keypoint_graph, keypoint_outputs, write_graph_artefact
from test_vo_odometry import BLANK, CAMERA, SyntheticExtractor, straight_then_turn
from vo_runtime import (ArtefactError, CalibrationError, Camera, ConcurrentUseError, FeatureExtractor,
                        OrbExtractor, TimestampError, VisualOdometry, VORuntimeError, load_camera,
                        write_trajectory)

SIDE = 32


def graph_artefact(space: Space, name: str = "art", dim: int | None = 8, graph_side: int = SIDE,
                   manifest: dict | None = None, **outputs) -> Path:
    """An artefact whose checksum matches but whose graph returns ``outputs`` (changed from well-formed ones);
    an output given as None is left out of the graph."""
    values = {**keypoint_outputs(), **outputs}
    values = {key: value for key, value in values.items() if value is not None}
    model = constant_keypoint_graph(graph_side, graph_side, values)
    return write_graph_artefact(space.root / name, model, SIDE, SIDE, dim=dim, **(manifest or {}))


def nan_keypoints() -> np.ndarray:
    points = keypoint_outputs()["keypoints"].copy()
    points[1] = np.nan
    return points


def garbage_graph(space: Space, data: bytes) -> Path:
    """A valid artefact folder whose model.onnx is replaced by ``data``, its checksum recorded again."""
    import json

    from vo_runtime.artefact import sha256_file

    folder = space.artefact_copy()
    (folder / "model.onnx").write_bytes(data)
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["onnx"]["sha256"] = sha256_file(folder / "model.onnx")
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def truncated_graph(space: Space) -> Path:
    return garbage_graph(space, (space.assets.artefact / "model.onnx").read_bytes()[:3000])


def outside_file(space: Space, absolute: bool) -> Path:
    """An artefact whose manifest points at a model file outside it (with the right checksum)."""
    folder = graph_artefact(space)
    outside = space.root / "elsewhere.onnx"
    outside.write_bytes((folder / "model.onnx").read_bytes())
    import json

    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["onnx"]["file"] = str(outside) if absolute else "../elsewhere.onnx"
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def sequence_with_times(space: Space, text: str) -> Path:
    root = space.sequence()
    (root / "times.txt").write_text(text)
    return root


def profile_with(space: Space, field: str, value: str) -> Path:
    from profiles import load_profile

    source = Path(load_profile("x86-cpu").source).read_text()
    lines = [f"{field} = {value}" if line.startswith(f"{field} =") else line for line in source.splitlines()]
    return space.file("host.toml", "\n".join(lines).encode())


def pairs_of_two_sizes(space: Space) -> Path:
    space.images("pairs/low", 1, 96)
    space.images("pairs/high", 1, 64)
    return space.root / "pairs"


def vo(space: Space, artefact: Path) -> list:
    return ["vo", "--artefact", artefact, "--images", space.sequence(), "--no-progress"]


def orb_on(sequence: Path) -> list:
    return ["vo", "--features", "orb", "--images", sequence, "--no-progress"]


CASES: list[tuple[str, str, Callable[[Space], list]]] = [
    # D6: graph outputs against the manifest
    ("vo-num-valid-negative", "num_valid = -5", lambda s: vo(s, graph_artefact(s, num_valid=np.array([-5], np.int32)))),
    ("vo-num-valid-huge", "num_valid = 1000000000",
     lambda s: vo(s, graph_artefact(s, num_valid=np.array([10 ** 9], np.int32)))),
    ("vo-descriptors-of-another-width", "descriptors output is [16, 128]",
     lambda s: vo(s, graph_artefact(s, descriptors=np.ones((16, 128), np.float32)))),
    ("vo-keypoints-k3", "keypoints output is [16, 3]",
     lambda s: vo(s, graph_artefact(s, keypoints=np.ones((16, 3), np.float32)))),
    ("vo-nan-keypoints", "NaN or infinite", lambda s: vo(s, graph_artefact(s, keypoints=nan_keypoints()))),
    ("vo-negative-scale", "scale must be a positive number",
     lambda s: vo(s, graph_artefact(s, manifest={"input__normalisation": {"scale": -1 / 255}}))),
    # D17: a checksum that matches a bad graph
    ("vo-nan-scale", "scale must be a positive number",
     lambda s: vo(s, graph_artefact(s, manifest={"input__normalisation": {"scale": float("nan")}}))),
    ("vo-graph-input-unlike-manifest", "the graph's input is [1, 1, 48, 48]",
     lambda s: vo(s, graph_artefact(s, graph_side=48))),
    ("vo-graph-without-num-valid", "has no num_valid output", lambda s: vo(s, graph_artefact(s, num_valid=None))),
    ("vo-garbage-graph", "onnxruntime cannot load", lambda s: vo(s, garbage_graph(s, b"not a graph"))),
    ("quantise-garbage-graph", "no valid ONNX graph",
     lambda s: ["quantise", "--artefact", garbage_graph(s, b"not a graph"), "--mode", "int8", "-o", s.root / "q"]),
    ("quantise-truncated-graph", "no valid ONNX graph",
     lambda s: ["quantise", "--artefact", truncated_graph(s), "--mode", "int8", "-o", s.root / "q"]),
    ("profile-garbage-graph", "no valid ONNX graph",
     lambda s: ["profile", "--model", garbage_graph(s, b"not a graph"), "--no-compare"]),
    ("profile-graph-without-output", "has no num_valid output",
     lambda s: ["profile", "--model", graph_artefact(s, num_valid=None), "--no-compare"]),
    ("eval-num-valid-negative", "num_valid = -5",
     lambda s: ["eval", "pairs", "--data", PAIRS, "--model", graph_artefact(s, num_valid=np.array([-5], np.int32))]),
    # D26: the model file lies inside the artefact
    ("vo-onnx-file-above", "must name a file inside the artefact", lambda s: vo(s, outside_file(s, absolute=False))),
    ("vo-onnx-file-absolute", "must name a file inside the artefact", lambda s: vo(s, outside_file(s, absolute=True))),
    # D23: a missing mode is no dense artefact
    ("vo-manifest-without-mode", "records no mode", lambda s: vo(s, graph_artefact(s, manifest={"mode": None}))),
    # D7: timestamps
    ("vo-nan-times", "not a finite number", lambda s: orb_on(sequence_with_times(s, "nan\nnan\nnan\n"))),
    ("vo-repeated-times", "repeats", lambda s: orb_on(sequence_with_times(s, "0.0\n0.0\n0.2\n"))),
    ("vo-decreasing-times", "goes back", lambda s: orb_on(sequence_with_times(s, "0.0\n0.2\n0.1\n"))),
    # D8: hardware figures that are no numbers
    ("profile-nan-peak", "must be a finite number",
     lambda s: ["profile", "--target", profile_with(s, "peak_gflops_fp32", "nan"), "--input-size", "32x48"]),
    ("profile-minus-inf-bandwidth", "must be a finite number",
     lambda s: ["profile", "--target", profile_with(s, "memory_bandwidth_gbs", "-inf"), "--input-size", "32x48"]),
    # D9: the identity registers only images of one size
    ("eval-pairs-of-two-sizes", "the identity fits only images of one size",
     lambda s: ["eval", "pairs", "--data", pairs_of_two_sizes(s), "--model", "orb"]),
]


@pytest.mark.parametrize("name, fragment, build", CASES, ids=[case[0] for case in CASES])
def test_result_row_is_one_error_line_and_changes_nothing(name, fragment, build, bad_input_assets, tmp_path, capsys):
    argv = build(Space(tmp_path, bad_input_assets))
    assert_refused(toolkit.cli.main, argv, capsys, fragment, tmp_path, bad_input_assets.root)


# ------------------------------------------------------------------------------------------------ the API
API_CASES: list[tuple[str, type, Callable[[], object]]] = [
    ("extractor-none", ArtefactError, lambda: FeatureExtractor(None)),
    ("load-camera-none", CalibrationError, lambda: load_camera(None)),
    ("vo-camera-none", CalibrationError, lambda: VisualOdometry(OrbExtractor(100), None)),
    ("vo-extractor-not-callable", VORuntimeError, lambda: VisualOdometry(42, CAMERA)),
    ("camera-width-text", CalibrationError, lambda: Camera(500.0, 500.0, 320.0, 240.0, width="wide", height=480)),
    ("camera-width-fraction", CalibrationError, lambda: Camera(500.0, 500.0, 320.0, 240.0, width=12.7, height=480)),
    ("camera-fx-bool", CalibrationError, lambda: Camera(True, 500.0, 320.0, 240.0)),
    ("camera-dist-text", CalibrationError, lambda: Camera(500.0, 500.0, 320.0, 240.0, dist="k1")),
    ("trajectory-csv", VORuntimeError, lambda: write_trajectory("t.csv", [], fmt="csv")),
    ("trajectory-path-none", VORuntimeError, lambda: write_trajectory(None, [])),
]


@pytest.mark.parametrize("name, error, call", API_CASES, ids=[case[0] for case in API_CASES])
def test_api_row_is_a_typed_error(name, error, call, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(error):
        call()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", ["num-valid", "descriptors", "nan-scale", "input", "outside"])
def test_api_bad_graph_is_an_artefact_error_at_load(name, tmp_path):
    space = Space(tmp_path, None)
    build = {"num-valid": lambda: graph_artefact(space, num_valid=np.array([-5], np.int32)),
             "descriptors": lambda: graph_artefact(space, descriptors=np.ones((16, 128), np.float32)),
             "nan-scale": lambda: graph_artefact(space, manifest={"input__normalisation": {"scale": float("nan")}}),
             "input": lambda: graph_artefact(space, graph_side=48),
             "outside": lambda: outside_file(space, absolute=False)}[name]
    with pytest.raises(ArtefactError):
        FeatureExtractor(build())


def test_a_well_formed_graph_gives_its_valid_rows(tmp_path):
    features = FeatureExtractor(graph_artefact(Space(tmp_path, None)))(np.zeros((SIDE, SIDE), np.uint8))
    assert len(features) == 4 and features.descriptors.shape == (4, 8)


def test_numpy_intrinsics_are_numbers():
    """D23: np.float32 intrinsics were refused as 'not finite'."""
    camera = Camera(np.float32(500), np.float64(500), np.float32(319.5), 239.5, width=np.int64(640), height=480)
    assert type(camera.fx) is float and camera.width == 640


@pytest.mark.parametrize("stamp", [float("nan"), float("inf"), "0.5", True, 1.0, 0.5])
def test_a_bad_timestamp_is_refused_and_changes_nothing(stamp):
    """D7: after a frame at t = 1.0, a NaN, infinite, text, bool, repeated or earlier stamp is refused."""
    vo = VisualOdometry(SyntheticExtractor(straight_then_turn(5)), CAMERA)
    vo.track(BLANK, timestamp=1.0)
    with pytest.raises(TimestampError):
        vo.track(BLANK, timestamp=stamp)
    assert [r.index for r in vo.results] == [0]
    assert vo.track(BLANK, timestamp=2.0).index == 1
    assert vo.track(None, timestamp=3.0).status == "skipped"  # a skipped frame's stamp is checked too
    with pytest.raises(TimestampError):
        vo.track(None, timestamp=2.5)


def test_track_from_a_second_thread_is_refused():
    """D5: while one thread is inside track, another is refused with a typed error; nothing interleaves."""
    inside, release = threading.Event(), threading.Event()
    synthetic = SyntheticExtractor(straight_then_turn(5))

    def slow_extractor(image):
        inside.set()
        assert release.wait(10)
        return synthetic(image)

    vo = VisualOdometry(slow_extractor, CAMERA)
    first = threading.Thread(target=vo.track, args=(BLANK, 0.0))
    first.start()
    assert inside.wait(10)
    with pytest.raises(ConcurrentUseError, match="another thread"):
        vo.track(BLANK, 1.0)
    release.set()
    first.join(10)
    assert [r.index for r in vo.results] == [0]
    assert vo.track(BLANK, 1.0).index == 1  # the instance is usable again from any thread
