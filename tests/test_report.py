"""The table a run ends with: mean xi per model x adverse condition, the best of each column marked."""
from __future__ import annotations

import json
import math

from pairedgta.report import xi_lines


def _evaluation(folder, xi, teacher="ref", model=None):
    folder.mkdir()
    (folder / "summary.json").write_text(json.dumps({"reference_model": teacher, "xi_mean": xi,
                                                     "model": model or folder.name}))
    return str(folder)


def test_rows_per_model_columns_per_adverse_condition_and_the_best_marked(tmp_path):
    evals = {"a": _evaluation(tmp_path / "a", {"Day-EXTRASUNNY": 1.0, "Day-RAIN": 0.61, "Night-RAIN": 0.2}),
             "bb": _evaluation(tmp_path / "b", {"Day-EXTRASUNNY": 0.9, "Day-RAIN": 0.5, "Night-RAIN": math.nan})}
    lines = xi_lines(evals, reference="Day-EXTRASUNNY")
    assert lines[0].split() == ["mean", "xi", "Day-RAIN", "Night-RAIN"]  # the clean reference is no column
    assert lines[1].split() == ["a", "0.610*", "0.200*"]
    assert lines[2].split() == ["bb", "0.500", "-"]  # NaN (no supported class) is a dash, never a best
    assert lines[3] == "(against ref's pseudo-labels on Day-EXTRASUNNY; * best per condition)"


def test_one_model_has_no_marks_and_no_summary_no_table(tmp_path):
    lines = xi_lines({"a": _evaluation(tmp_path / "a", {"Day-RAIN": 0.5})})
    assert "*" not in "".join(lines[:2]) and lines[-1] == "(against ref's pseudo-labels)"
    assert xi_lines({"a": str(tmp_path / "missing")}) == []


def test_the_reference_is_shown_as_the_reference_and_never_marked(tmp_path):
    """The main job evaluates its reference model too: graded on its own pseudo-labels it would be the best
    of nearly every column. Its row comes last, named the reference, without a star; the best is marked
    among the others."""
    evals = {"ref": _evaluation(tmp_path / "ref", {"Day-RAIN": 0.95, "Night-RAIN": 0.90}),
             "a": _evaluation(tmp_path / "a", {"Day-RAIN": 0.61, "Night-RAIN": 0.20}),
             "b": _evaluation(tmp_path / "b", {"Day-RAIN": 0.50, "Night-RAIN": 0.30})}
    lines = xi_lines(evals, reference="Day-EXTRASUNNY")
    assert lines[1].split() == ["a", "0.610*", "0.200"]
    assert lines[2].split() == ["b", "0.500", "0.300*"]
    assert lines[3].split() == ["ref", "(reference)", "0.950", "0.900"]
    assert lines[4] == ("(against ref's pseudo-labels on Day-EXTRASUNNY; * best per condition among the other models; "
                        "the reference grades its own pseudo-labels: not ranked)")
    # the reference and one other model: nothing to rank, no star at all
    lines = xi_lines({k: evals[k] for k in ("ref", "a")}, reference="Day-EXTRASUNNY")
    assert "*" not in "".join(lines) and lines[2].split()[:2] == ["ref", "(reference)"]


def test_a_detection_table_shows_the_reference_boxes_each_column_rests_on(tmp_path):
    """Detection xi's mean rests on a few dozen reference boxes: the count is under each column header, one
    number where every model's mean rests on the same boxes, the range where a model blind to a class rests
    on fewer; a segmentation summary (no xi_support) has no such row."""
    def det(folder, xi, support):
        folder.mkdir()
        (folder / "summary.json").write_text(json.dumps({"task": "detection", "reference_model": "ref",
                                                         "model": folder.name, "xi_mean": xi,
                                                         "xi_support": support}))
        return str(folder)

    evals = {"a": det(tmp_path / "a", {"Day-EXTRASUNNY": 1.0, "Day-RAIN": 0.6, "Night-RAIN": 0.2},
                      {"Day-EXTRASUNNY": 31, "Day-RAIN": 31, "Night-RAIN": 31}),
             "b": det(tmp_path / "b", {"Day-EXTRASUNNY": 1.0, "Day-RAIN": 0.5, "Night-RAIN": 0.3},
                      {"Day-EXTRASUNNY": 22, "Day-RAIN": 31, "Night-RAIN": 22})}
    lines = xi_lines(evals, reference="Day-EXTRASUNNY")
    assert lines[0].split() == ["mean", "detection", "xi", "Day-RAIN", "Night-RAIN"]
    assert lines[1].split() == ["(reference", "boxes)", "31", "22-31"]
    assert lines[2].split() == ["a", "0.600*", "0.200"]
    seg = xi_lines({"a": _evaluation(tmp_path / "s", {"Day-RAIN": 0.5})})
    assert not any("reference boxes" in line for line in seg)
