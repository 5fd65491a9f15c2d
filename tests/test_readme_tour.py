"""The README's tour as a new user meets it: every line of its first block run as written, in order, from a folder
laid out like the repository (``../shared/data`` beside it, ``.venv`` and ``bench/`` in it); the full-size forms
of the second block parsed by the toolkit's own parser, with their inputs present and their outputs chained."""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest

from toolkit.cli import build_parser

REPO = Path(__file__).resolve().parents[1]
TOUR_HEADING = "## A short tour"
# Commands whose last line of output must say where they wrote, and the option naming that place.
OUTPUT_OPTIONS = {"label": "--out", "train": "--out", "export": "-o", "profile": "-o", "eval": "-o", "prune": "-o",
                  "quantise": "-o"}


def tour_blocks(readme: str) -> list[list[str]]:
    """The tour's ```bash blocks, each as its command lines (continuations joined, comment lines dropped)."""
    section = readme.split(TOUR_HEADING, 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```bash\n(.*?)```", section, flags=re.S)
    commands = []
    for block in blocks:
        joined = block.replace("\\\n", " ")
        commands.append([line.strip() for line in joined.splitlines() if line.strip() and not line.strip().startswith("#")])
    return commands


def toolkit_argv(command: str) -> list[str] | None:
    """The toolkit arguments of a `toolkit ...` or `torchrun ... -m toolkit ...` line (comments dropped), else None."""
    words = shlex.split(command, comments=True)
    if words[:1] == ["toolkit"]:
        return words[1:]
    if words[:1] == ["torchrun"] and "toolkit" in words:
        return words[words.index("toolkit") + 1:]
    return None


def option(argv: list[str], name: str) -> str | None:
    return argv[argv.index(name) + 1] if name in argv else None


@pytest.fixture(scope="module")
def tour_root(tmp_path_factory: pytest.TempPathFactory, shared_data: Path) -> Path:
    """A folder that looks like a fresh clone to the tour: ../shared beside it, its own .venv and bench/ inside."""
    root = tmp_path_factory.mktemp("tour")
    (root / "shared").symlink_to(shared_data.parent)
    clone = root / "edgefeat"
    clone.mkdir()
    (clone / ".venv").symlink_to(Path(sys.prefix))
    (clone / "bench").symlink_to(REPO / "bench")
    return clone


def test_the_readme_tour_runs_as_written(tour_root: Path) -> None:
    first, _ = tour_blocks((REPO / "README.md").read_text())
    assert first[0] == ". .venv/bin/activate"
    env = {key: value for key, value in os.environ.items() if key not in ("PYTHONPATH", "EDGEFEAT_DATA")}
    env.update(XDG_CACHE_HOME=str(tour_root / ".cache"), OMP_NUM_THREADS="1")  # the calibration lands here, not in ~
    timings = []
    for command in first:
        start = time.perf_counter()
        result = subprocess.run(["bash", "-c", f". .venv/bin/activate && {command}"], cwd=tour_root, env=env,
                                capture_output=True, text=True)
        timings.append(f"{time.perf_counter() - start:6.1f} s  {command[:100]}")
        assert result.returncode == 0, f"{command}\n{result.stderr[-3000:]}"
        argv = toolkit_argv(command.split(" && ")[-1])
        if argv and argv[0] in OUTPUT_OPTIONS and option(argv, OUTPUT_OPTIONS[argv[0]]) and "torchrun" not in command:
            last = result.stdout.strip().splitlines()[-1]
            assert option(argv, OUTPUT_OPTIONS[argv[0]]) in last, f"{command}: the last line says {last!r}"
    print("\n".join(timings))
    # every artefact the tour wrote carries its references, and this runtime reproduces them
    for artefact in ("out/tx2", "out/cpu", "out/cpu-int8", "out/tx2-fp16"):
        result = subprocess.run([sys.executable, "-m", "vo_runtime", "verify", artefact, "--providers", "cpu"],
                                cwd=tour_root, env=env, capture_output=True, text=True)
        assert result.returncode == 0, f"verify {artefact}: {result.stderr}"


def test_the_full_size_forms_parse_and_chain(shared_data: Path) -> None:
    _, full = tour_blocks((REPO / "README.md").read_text())
    parser = build_parser()
    written: set[str] = set()
    for command in full:
        argv = toolkit_argv(command)
        assert argv is not None, command
        parser.parse_args(argv)  # a bad option would exit here
        for name in ("--images", "--data"):
            if option(argv, name):
                assert (REPO / option(argv, name)).exists(), f"{command}: {option(argv, name)} is missing"
        for name in ("--labels", "--checkpoint"):
            if option(argv, name):  # what a line reads was written by a line before it
                assert any(option(argv, name).startswith(place) for place in written), f"{command}: nothing writes {name}"
        written.update(value for value in (option(argv, "--out"), option(argv, "-o")) if value)
