"""The package as users get it: profiles inside a non-editable install, and a CLI that explains itself."""
from __future__ import annotations

import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from toolkit.cli import COMMAND_MODULES, build_parser

REPO = Path(__file__).resolve().parents[1]


def test_profiles_reach_a_non_editable_install(tmp_path):
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "wheel"), str(REPO)],
        check=True, capture_output=True,
    )
    wheel = next((tmp_path / "wheel").glob("edgefeat-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert {"profiles/tx2.toml", "profiles/x86-cpu.toml"} <= set(names)
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)], check=True, capture_output=True)
    probe = "import profiles; print(profiles.__file__); print(profiles.load_profile('tx2').max_opset)"
    result = subprocess.run(
        [sys.executable, "-c", probe], cwd=tmp_path, capture_output=True, text=True, check=True,
        env={**os.environ, "PYTHONPATH": str(target)},
    )
    location, opset = result.stdout.split()
    assert location.startswith(str(target)) and opset == "13"


def test_help_lists_every_subcommand_with_examples(capsys):
    parser = build_parser()
    with pytest.raises(SystemExit):
        parser.parse_args(["--help"])
    top = capsys.readouterr().out
    names = [module.rsplit("cmd_", 1)[1] for module in COMMAND_MODULES]
    for name in names:
        assert name in top
        with pytest.raises(SystemExit):
            parser.parse_args([name, "--help"])
        assert "example" in capsys.readouterr().out.lower()


def test_a_non_editable_install_exports_the_shipped_model_without_shared_data(tmp_path):
    """A fresh virtualenv holding only the wheel (its dependencies reached through a .pth file, so nothing
    is downloaded), run from a folder with no ../shared beside it: `toolkit export` needs no --checkpoint
    and no parity images for either target, and the wheel carries the weights, cards and images."""
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(tmp_path / "wheel"), str(REPO)],
        check=True, capture_output=True,
    )
    wheel = next((tmp_path / "wheel").glob("edgefeat-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    for shipped in ("models/weights/featurenet-elu.safetensors", "models/weights/featurenet-relu.safetensors",
                    "models/weights/MODEL_CARD-featurenet-elu.md", "export/parity_images/PROVENANCE.md",
                    "export/parity_images/hopper.png", "vo_runtime/default_artefact/model.onnx",
                    "vo_runtime/default_artefact/manifest.json", "vo_runtime/default_artefact_wide/model.onnx",
                    "vo_runtime/default_artefact_wide/manifest.json"):
        assert shipped in names, shipped
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    site = next((venv / "lib").glob("python3*/site-packages"))
    import sysconfig

    # The dependencies only (a path in a .pth does not run that folder's own .pth files, so the editable
    # checkout of this repository stays invisible).
    (site / "deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    # --ignore-installed: otherwise pip uninstalls the running environment's own (editable) edgefeat first
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--ignore-installed", "-q", "--prefix",
                    str(venv), str(wheel)], check=True, capture_output=True)
    work = tmp_path / "elsewhere" / "cwd"
    work.mkdir(parents=True)
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "EDGEFEAT_DATA")}
    python = str(venv / "bin" / "python")
    where = subprocess.run([python, "-c", "import models.weights as w; print(w.__file__)"], cwd=work, env=env,
                           capture_output=True, text=True, check=True).stdout.strip()
    assert where.startswith(str(venv)), where
    for target in ("tx2", "x86-cpu"):
        result = subprocess.run([python, "-m", "toolkit", "export", "--target", target, "-o", f"out/{target}"], cwd=work,
                                env=env, capture_output=True, text=True)
        assert result.returncode == 0, result.stderr[-2000:]
        assert (work / "out" / target / "model.onnx").is_file()
