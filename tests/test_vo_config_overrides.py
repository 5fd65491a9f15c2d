"""``--set FIELD=VALUE`` of the vo command: the knob reaches the VO, typed as its field, and the run says so."""
from __future__ import annotations

import json

import pytest

import vo_runtime.cli
from vo_runtime.config_overrides import config_from_overrides
from vo_runtime.errors import VORuntimeError


def test_values_take_their_fields_types():
    config, applied = config_from_overrides(
        ["init_wanted_landmarks=100", "probation_max_deg=1", "match_ratio=null", "mapping_thread=true",
         "mapping.min_parallax_px=9"], mapping_thread=False)
    assert config.init_wanted_landmarks == 100 and isinstance(config.probation_max_deg, float)
    assert config.match_ratio is None and config.mapping_thread is True
    assert config.mapping.min_parallax_px == 9.0 and config.mapping.ba_keyframes == 5  # the rest left alone
    assert applied == {"init_wanted_landmarks": 100, "probation_max_deg": 1.0, "match_ratio": None,
                       "mapping_thread": True, "mapping.min_parallax_px": 9.0}
    with pytest.raises(VORuntimeError, match="takes true or false"):
        config_from_overrides(["mapping_thread=1"])
    with pytest.raises(VORuntimeError, match="has no field 'mapping'"):
        config_from_overrides(["mapping=1"])


def test_a_knob_set_on_the_command_line_changes_the_run(shared_data, tmp_path):
    def run(name: str, *extra: str) -> tuple[dict, list[dict]]:
        output = tmp_path / name
        code = vo_runtime.cli.main(["--features", "orb", "--images", str(shared_data / "kitti_odom06_f000000-000050"),
                                    "--max-frames", "14", "--no-progress", "-o", str(output), *extra])
        assert code == 0
        return (json.loads((output / "summary.json").read_text()),
                json.loads((output / "frames.json").read_text()))

    summary, frames = run("default")
    assert summary["config"] == {} and any(f["state"] == "tracking" for f in frames)
    # A first map that asks for more landmarks than two frames can have never comes.
    summary, frames = run("strict", "--set", "init_min_landmarks=100000")
    assert summary["config"] == {"init_min_landmarks": 100000}
    assert all(f["state"] == "initialising" for f in frames)
