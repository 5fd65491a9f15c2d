"""The graph for this CPU's channel blocks (`vo_runtime.cpu_blocks`): which block a CPU has, which file an artefact
gives for it, that the extractor and `verify` load that file, and that a missing or changed one is refused."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

import vo_runtime.cpu_blocks as cpu_blocks
from vo_runtime.artefact import WIDE_ARTEFACT_DIR, verify_artefact
from vo_runtime.cpu_blocks import graph_file, nchwc_block
from vo_runtime.errors import ArtefactError


def test_the_block_follows_the_cpu(tmp_path) -> None:
    assert nchwc_block({"sse4_2", "avx2", "fma", "avx512f", "avx512bw"}, "x86_64") == 16
    assert nchwc_block({"sse4_2", "avx2", "fma"}, "x86_64") == 8
    assert nchwc_block({"asimd", "fp"}, "aarch64") == 1  # onnxruntime blocks channels on x86 only
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nmodel name\t: AMD EPYC 7B13\nflags\t\t: fpu sse2 avx2 avx512f\n\n"
                       "processor\t: 1\nflags\t\t: fpu\n")
    assert "avx512f" in cpu_blocks.cpu_flags(cpuinfo)
    assert cpu_blocks.cpu_name(cpuinfo) == "AMD EPYC 7B13"
    assert cpu_blocks.cpu_flags(tmp_path / "missing") == set() and cpu_blocks.cpu_name(tmp_path / "missing")


def test_an_artefact_names_the_graph_for_each_block() -> None:
    manifest = verify_artefact(WIDE_ARTEFACT_DIR)
    assert graph_file(manifest, 16) == "model.block16.onnx"
    assert graph_file(manifest, 8) == graph_file(manifest, 1) == "model.onnx"
    assert graph_file({"onnx": {"file": "model.onnx"}}, 16) == "model.onnx"  # an artefact before block graphs


@pytest.mark.parametrize("block", [8, 16])
def test_the_extractor_and_verify_run_the_graph_for_the_block(block, monkeypatch, capsys) -> None:
    from vo_runtime import FeatureExtractor
    from vo_runtime.verify import main as verify_main

    monkeypatch.setattr(cpu_blocks, "nchwc_block", lambda: block)
    extractor = FeatureExtractor(WIDE_ARTEFACT_DIR)
    assert extractor.graph == ("model.block16.onnx" if block == 16 else "model.onnx")
    assert verify_main([str(WIDE_ARTEFACT_DIR), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["graph"] == extractor.graph


def test_both_graphs_find_the_same_features_on_a_drone_frame(monkeypatch, shared_data) -> None:
    import cv2

    from vo_runtime import FeatureExtractor

    frame = sorted((shared_data / "euroc_mh05_f000000-000199" / "mav0" / "cam0" / "data").glob("*.png"))[60]
    image = (cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE) * 0.2).astype(np.uint8)  # dark, as the mission flies
    found = []
    for block in (8, 16):
        monkeypatch.setattr(cpu_blocks, "nchwc_block", lambda block=block: block)
        found.append(FeatureExtractor(WIDE_ARTEFACT_DIR)(image))
    assert len(found[0].keypoints) == len(found[1].keypoints) > 100
    np.testing.assert_allclose(found[1].keypoints, found[0].keypoints, atol=1e-4)
    np.testing.assert_allclose(found[1].descriptors, found[0].descriptors, atol=1e-4)


@pytest.mark.parametrize("damage", ["missing", "changed", "outside"])
def test_a_missing_or_changed_block_graph_is_refused(damage, tmp_path) -> None:
    copy = tmp_path / "artefact"
    shutil.copytree(WIDE_ARTEFACT_DIR, copy)
    if damage == "missing":
        (copy / "model.block16.onnx").unlink()
    elif damage == "changed":
        with open(copy / "model.block16.onnx", "ab") as handle:
            handle.write(b"\0")
    else:
        manifest = json.loads((copy / "manifest.json").read_text())
        manifest["onnx"]["block_graphs"][0]["file"] = "../model.onnx"
        (copy / "manifest.json").write_text(json.dumps(manifest))
    message = {"missing": "model.block16.onnx is missing", "changed": "fails its manifest checksum",
               "outside": "must name a file inside the artefact"}[damage]
    with pytest.raises(ArtefactError, match=message):
        verify_artefact(copy)
