"""The runtime-only install: the wheel without extras runs the VO on a real sequence and never sees torch.

A fresh virtualenv gets the wheel (no extras) and exactly the distributions its base requirements pull in,
resolved from the wheel's own metadata (so nothing is downloaded: each is linked from this environment).
Torch, onnx, evo, matplotlib and tqdm are therefore not importable there at all.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import zipfile
from email.parser import Parser
from importlib import metadata
from pathlib import Path

import pytest
from packaging.requirements import Requirement

REPO = Path(__file__).resolve().parents[1]
RUNTIME_REQUIREMENTS = {"numpy", "opencv-python-headless", "scipy", "onnxruntime", "threadpoolctl", "pyyaml"}


def _base_requirements(wheel: Path) -> list[Requirement]:
    with zipfile.ZipFile(wheel) as archive:
        name = next(n for n in archive.namelist() if n.endswith(".dist-info/METADATA"))
        fields = Parser().parsestr(archive.read(name).decode())
    requirements = [Requirement(line) for line in fields.get_all("Requires-Dist") or []]
    return [r for r in requirements if r.marker is None or r.marker.evaluate({"extra": ""})]


def _closure(requirements: list[Requirement]) -> list[metadata.Distribution]:
    """The installed distributions these requirements pull in, transitively (no extras)."""
    seen: dict[str, metadata.Distribution] = {}
    todo = list(requirements)
    while todo:
        requirement = todo.pop()
        key = requirement.name.lower().replace("_", "-")
        if key in seen:
            continue
        dist = metadata.distribution(requirement.name)
        seen[key] = dist
        todo += [r for r in map(Requirement, dist.requires or []) if r.marker is None or r.marker.evaluate({"extra": ""})]
    return list(seen.values())


def _link_distributions(dists: list[metadata.Distribution], folder: Path) -> None:
    """Symlink each distribution's top-level files and folders (and its .dist-info) into ``folder``."""
    folder.mkdir()
    for dist in dists:
        tops = {Path(str(f)).parts[0] for f in dist.files or [] if not str(f).startswith("..")}
        for top in tops:
            source = Path(str(dist.locate_file(top)))
            if source.exists() and not (folder / top).exists() and top != "__pycache__":
                (folder / top).symlink_to(source)


@pytest.fixture(scope="module")
def runtime_venv(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("runtime")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w",
                    str(root / "wheel"), str(REPO)], check=True, capture_output=True)
    wheel = next((root / "wheel").glob("edgefeat-*.whl"))
    requirements = _base_requirements(wheel)
    assert {r.name for r in requirements} == RUNTIME_REQUIREMENTS  # the base install is the runtime, no more
    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    site = next((venv / "lib").glob("python3*/site-packages"))
    _link_distributions(_closure(requirements), root / "deps")
    (site / "runtime-deps.pth").write_text(str(root / "deps") + "\n")
    # --ignore-installed: without it pip first uninstalls the edgefeat of the environment running the tests
    # (the developer's editable install), even though it installs into another prefix.
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--ignore-installed", "-q", "--prefix",
                    str(venv), str(wheel)], check=True, capture_output=True)
    work = root / "elsewhere"
    work.mkdir()
    return venv, work


def _run(venv: Path, work: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "EDGEFEAT_DATA")}
    return subprocess.run([str(venv / "bin" / "python"), *args], cwd=work, env=env, capture_output=True, text=True)


def test_the_runtime_runs_the_vo_on_a_real_sequence_without_torch(runtime_venv, shared_data: Path) -> None:
    venv, work = runtime_venv
    sequence = shared_data / "kitti_odom06_f000000-000050"
    probe = (
        "import importlib.util, json, sys\n"
        "from vo_runtime import VisualOdometry\n"
        "from vo_runtime.cli import main\n"
        f"code = main(['--images', {str(sequence)!r}, '--max-frames', '20', '--json', '-o', 'run'])\n"
        "print(json.dumps({'code': code, 'torch_loaded': 'torch' in sys.modules,\n"
        "                  'torch_installed': importlib.util.find_spec('torch') is not None,\n"
        "                  'vo': VisualOdometry.__module__, 'where': sys.modules['vo_runtime'].__file__}))\n"
    )
    result = _run(venv, work, "-c", probe)
    assert result.returncode == 0, result.stderr[-2000:]
    summary, report = (json.loads(line) for line in result.stdout.strip().splitlines()[-2:])
    assert report["code"] == 0 and not report["torch_loaded"] and not report["torch_installed"]
    assert report["where"].startswith(str(venv))
    assert summary["frames"] == 20 and summary["providers"] == "cpu"
    assert summary["states"].get("tracking", 0) >= 5  # the shipped artefact tracks a real KITTI sequence
    assert (work / "run" / "trajectory_tum.txt").is_file() and not (work / "run" / "trajectory.png").exists()


def test_the_runtime_install_names_the_extras_it_lacks(runtime_venv, shared_data: Path) -> None:
    venv, work = runtime_venv
    # The console script, run by the venv's interpreter (pip ran from this environment wrote its shebang).
    toolkit = _run(venv, work, str(venv / "bin" / "toolkit"), "export", "--target", "tx2", "-o", "out")
    assert toolkit.returncode == 2 and toolkit.stdout == ""
    lines = toolkit.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: toolkit needs the 'edgefeat[toolkit]' extra")
    assert "torch" in lines[0] and not (work / "out").exists()
    gt = _run(venv, work, "-m", "vo_runtime", "--images", str(shared_data / "kitti_odom07_f000000-000159"),
              "--gt", "auto", "--max-frames", "3")
    lines = gt.stderr.strip().splitlines()
    assert gt.returncode == 2 and len(lines) == 1 and "edgefeat[eval]" in lines[0]
