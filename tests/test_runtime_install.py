"""The runtime-only install: the edgefeat-runtime wheel (built from runtime/) puts only vo_runtime on the path,
runs the VO on a real sequence and never sees torch; the full edgefeat wheel without extras names the extra
its toolkit lacks.

A fresh virtualenv gets a wheel (no extras) and exactly the distributions its base requirements pull in,
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
TOOLKIT_PACKAGES = ("models", "export", "profiles", "toolkit")


def build_wheel(source: Path, folder: Path) -> Path:
    """``pip wheel`` of one of the two distributions (the repository root, or runtime/), as the README says."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(folder),
                    str(source)], check=True, capture_output=True)
    return next(folder.glob("*.whl"))


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


def _install_in_fresh_venv(wheel: Path, root: Path) -> Path:
    """A virtualenv under ``root`` holding ``wheel`` and the installed distributions of its base requirements."""
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
    (root / "elsewhere").mkdir()
    return venv


@pytest.fixture(scope="module")
def wheels(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("wheels")
    return {"runtime": build_wheel(REPO / "runtime", folder / "runtime"), "full": build_wheel(REPO, folder / "full")}


@pytest.fixture(scope="module")
def runtime_venv(tmp_path_factory: pytest.TempPathFactory, wheels: dict[str, Path]) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("runtime")
    return _install_in_fresh_venv(wheels["runtime"], root), root / "elsewhere"


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


def test_the_runtime_wheel_holds_vo_runtime_alone_at_the_version_of_the_tree(wheels: dict[str, Path]) -> None:
    from vo_runtime.version import __version__

    runtime, full = (zipfile.ZipFile(wheels[name]) for name in ("runtime", "full"))
    tops = {name.split("/")[0] for name in runtime.namelist()}
    assert tops == {"vo_runtime", f"edgefeat_runtime-{__version__}.dist-info"}
    assert "vo_runtime/default_artefact/model.onnx" in runtime.namelist()
    # the full wheel carries the very same runtime files, so either install gives the same vo_runtime
    runtime_files = {n for n in runtime.namelist() if n.startswith("vo_runtime/")}
    assert runtime_files == {n for n in full.namelist() if n.startswith("vo_runtime/")}
    assert all(runtime.read(n) == full.read(n) for n in runtime_files)
    assert wheels["full"].name.startswith(f"edgefeat-{__version__}-")
    assert _base_requirements(wheels["runtime"]) == _base_requirements(wheels["full"])


def test_only_vo_runtime_is_importable_from_the_runtime_install(runtime_venv) -> None:
    venv, work = runtime_venv
    probe = ("import importlib.util, json\n"
             f"print(json.dumps({{name: importlib.util.find_spec(name) is not None for name in {TOOLKIT_PACKAGES + ('vo_runtime',)!r}}}))")
    result = _run(venv, work, "-c", probe)
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout) == {**{name: False for name in TOOLKIT_PACKAGES}, "vo_runtime": True}
    assert not (venv / "bin" / "toolkit").exists()


def test_the_runtime_install_verifies_its_shipped_artefact_without_torch(runtime_venv) -> None:
    venv, work = runtime_venv
    site = next((venv / "lib").glob("python3*/site-packages"))
    result = _run(venv, work, "-m", "vo_runtime", "verify", str(site / "vo_runtime" / "default_artefact"), "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    assert json.loads(result.stdout)["passed"]


def test_the_runtime_install_names_the_extra_it_lacks(runtime_venv, shared_data: Path) -> None:
    venv, work = runtime_venv
    gt = _run(venv, work, "-m", "vo_runtime", "--images", str(shared_data / "kitti_odom07_f000000-000159"),
              "--gt", "auto", "--max-frames", "3")
    lines = gt.stderr.strip().splitlines()
    assert gt.returncode == 2 and len(lines) == 1 and "edgefeat[eval]" in lines[0]


def test_the_full_wheel_without_extras_names_the_toolkit_extra(tmp_path: Path, wheels: dict[str, Path]) -> None:
    venv = _install_in_fresh_venv(wheels["full"], tmp_path)
    work = tmp_path / "elsewhere"
    # The console script, run by the venv's interpreter (pip ran from this environment wrote its shebang).
    toolkit = _run(venv, work, str(venv / "bin" / "toolkit"), "export", "--target", "tx2", "-o", "out")
    assert toolkit.returncode == 2 and toolkit.stdout == ""
    lines = toolkit.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: toolkit needs the 'edgefeat[toolkit]' extra")
    assert "torch" in lines[0] and not (work / "out").exists()
