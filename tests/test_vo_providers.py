"""Execution providers: selection, the one-line error for a missing one, and reporting what really ran."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import onnxruntime as ort
import pytest

from vo_runtime import FeatureExtractor, VORuntimeError
from vo_runtime.artefact import default_artefact
from vo_runtime.cli import main as vo_main
from vo_runtime.providers import choose_providers, parse_providers

ALL = ["TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"]


def test_auto_takes_the_best_available_in_order(tmp_path: Path) -> None:
    chain = choose_providers(parse_providers("auto"), ALL, cache_dir=tmp_path / "engines")
    assert [name for name, _ in chain] == ALL
    tensorrt = chain[0][1]
    assert tensorrt["trt_fp16_enable"] and tensorrt["trt_engine_cache_enable"]
    assert tensorrt["trt_engine_cache_path"] == str(tmp_path / "engines")
    assert chain[1][1] == {} and chain[2][1] == {}
    # A CPU-only onnxruntime (this machine's): auto falls back to the CPU alone.
    assert choose_providers(["auto"], ["CPUExecutionProvider"]) == [("CPUExecutionProvider", {})]
    assert [n for n, _ in choose_providers(["auto"], ["CUDAExecutionProvider", "CPUExecutionProvider"])] == ALL[1:]


def test_an_explicit_list_is_kept_in_its_order_and_a_missing_provider_is_refused() -> None:
    assert [n for n, _ in choose_providers(parse_providers("cpu,cuda"), ALL)] == [ALL[2], ALL[1]]
    with pytest.raises(VORuntimeError, match="tensorrt is not available .*it has: cuda, cpu"):
        choose_providers(parse_providers(["tensorrt", "cpu"]), ALL[1:])


@pytest.mark.parametrize("text, message", [("gpu", "unknown execution provider 'gpu'"), (",", "no execution provider"),
                                           ("auto,cpu", "cannot be combined"), ("cpu,CPU", "listed twice")])
def test_bad_provider_lists_are_refused(text: str, message: str) -> None:
    with pytest.raises(VORuntimeError, match=message):
        parse_providers(text)


def test_the_extractor_reports_the_providers_its_session_really_uses(monkeypatch: pytest.MonkeyPatch) -> None:
    extractor = FeatureExtractor(default_artefact())
    assert extractor.providers == ["cpu"]
    with pytest.raises(VORuntimeError, match="cuda is not available"):
        FeatureExtractor(default_artefact(), providers="cuda,cpu")
    # An onnxruntime that claims GPU providers it cannot start: the session falls back to the CPU, and the
    # extractor reports the CPU, not what was asked for.
    monkeypatch.setattr(ort, "get_available_providers", lambda: ALL)
    monkeypatch.setenv("EDGEFEAT_CACHE", "/nonexistent-cache-root-for-test")
    monkeypatch.setattr(Path, "mkdir", lambda self, *a, **k: None)  # nothing written for the claimed TensorRT
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fallback = FeatureExtractor(default_artefact(), providers="auto")
    assert fallback.providers == ["cpu"]


def test_the_cli_reports_the_provider_and_refuses_a_missing_one(shared_data: Path, capsys, tmp_path: Path) -> None:
    sequence = shared_data / "kitti_odom06_f000000-000050"
    assert vo_main(["--images", str(sequence), "--max-frames", "3", "--no-progress", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["providers"] == "cpu"
    assert vo_main(["--images", str(sequence), "--providers", "tensorrt", "-o", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: execution provider tensorrt is not available")
    assert not (tmp_path / "run").exists()
