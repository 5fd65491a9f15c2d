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
