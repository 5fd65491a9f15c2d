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


def _words(text: str) -> str:
    return " ".join(text.split())


def test_the_jetson_steps_quote_the_artefact_readme_and_the_default_models_figures() -> None:
    import json

    from export.readme import artefact_readme
    from profiles import load_profile

    readme = _words((REPO / "README.md").read_text())
    manifest = json.loads((REPO / "vo_runtime" / "default_artefact" / "manifest.json").read_text())
    manifest.update(precision="fp16", precision_applied="tensorrt-build-flag", target="tx2")
    manifest["onnx"]["opset"] = 13
    trtexec = next(line for line in artefact_readme(manifest, load_profile("tx2")).splitlines() if "trtexec --onnx" in line)
    assert _words(trtexec) in readme  # one trtexec line, the artefact's own
    # export --target tx2 ships the ELU weights: the section quotes the ELU prediction first
    assert "7.35 ms (MAXN) / 7.72 ms (MAXQ) for the ELU network that `export --target tx2` ships" in readme


def test_the_readme_counts_are_the_models_counts() -> None:
    from toolkit.profiling.profile import count_model
    from toolkit.profiling.sources import resolve_model

    readme = _words((REPO / "README.md").read_text())
    counts = {name: count_model(resolve_model(name, None), 240, 320, 1024)
              for name in ("featurenet", "default", "default-relu", "superpoint")}
    assert f"{counts['featurenet']['parameters'] / 1e6:.3f} M parameters, {counts['featurenet']['macs'] / 1e9:.3f} GMACs" in readme
    assert (f"{counts['default']['parameters'] / 1e6:.3f} M and {counts['default']['macs'] / 1e9:.3f} GMACs (ELU) / "
            f"{counts['default-relu']['macs'] / 1e9:.3f} (ReLU)") in readme
    assert f"{counts['superpoint']['parameters'] / 1e6:.2f} M, {counts['superpoint']['macs'] / 1e9:.2f} GMACs" in readme


def test_eval_help_and_docs_name_the_same_default_models() -> None:
    from toolkit.eval_common import MODEL_HELP

    assert "(default: default orb sift)" in MODEL_HELP
    assert "default `default orb sift`" in (REPO / "docs" / "evaluation.md").read_text()
