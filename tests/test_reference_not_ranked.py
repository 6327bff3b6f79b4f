"""The reference model is never ranked as a subject (issue 49, item 7): evaluated in the main job, it is
scored against its own pseudo-labels, so every ranking shows it as the reference or leaves it out. The
terminal table is tests/test_report.py; here the models x conditions heatmap with its MLflow metrics, and
Table 1's bold."""
from __future__ import annotations

from types import SimpleNamespace

import pandas as pd

from pairedgta import schema
from pairedgta.figures import FigureOptions


def _evaluation(model: str, xi: dict[str, float], teacher: str = "ref"):
    summary = {"model": model, "reference_model": teacher, "xi_mean": xi, "gt_miou": {c: 0.5 for c in xi}}
    return SimpleNamespace(model=model, summary=lambda s=summary: s)


def test_the_heatmap_puts_the_reference_last_and_mlflow_leaves_its_xi_out(tmp_path):
    from pairedgta.figures.comparison import draw

    conds = {"Day-EXTRASUNNY": 1.0}
    p = SimpleNamespace(label="main", grid=SimpleNamespace(reference="Day-EXTRASUNNY"), pseudo=None, evaluations=[
        _evaluation("ref", {**conds, "Day-RAIN": 0.97, "Night-RAIN": 0.95}),
        _evaluation("a", {**conds, "Day-RAIN": 0.6, "Night-RAIN": 0.2}),
        _evaluation("b", {**conds, "Day-RAIN": 0.7, "Night-RAIN": 0.4})])
    files, metrics = draw([p], tmp_path, FigureOptions(["png"], 40, schema.parse({})))
    table = pd.read_csv(tmp_path / "xi_models.csv")
    assert table.groupby("model")["is_reference"].first().to_dict() == {"a": False, "b": False, "ref": True}
    assert "compare/xi_mean/Day-RAIN/b" in metrics and not any(k.startswith("compare/xi_mean/") and k.endswith("/ref")
                                                              for k in metrics)
    assert metrics["compare/gt_miou/Day-RAIN/ref"] == 0.5  # ground truth is no self-grading
    assert (tmp_path / "xi_models.png").is_file()


def test_table_one_never_bolds_the_reference(tmp_path):
    import pairedgta.figures.xi as xi_figure

    rows = []
    for model, value in (("ref", 0.99), ("a", 0.6), ("b", 0.7)):
        for cls, v in (("road", value), ("mean", value)):
            rows.append({"model": model, "reference_model": "ref", "condition": "Day-RAIN", "class_name": cls, "xi": v,
                         "in_mean": cls != "mean"})
    xi = pd.DataFrame(rows)
    own = xi_figure.self_graded(xi)
    assert own == {"ref"}
    xi_figure.write_tables(xi, "Day-EXTRASUNNY", tmp_path, own=own)
    md = (tmp_path / "table1_xi.md").read_text()
    assert "| ref (reference, not ranked) | 99.0 | 99.0 |" in md and "| b | **70.0** | **70.0** |" in md
    assert "among the models other than the reference" in md
    tex = (tmp_path / "table1_xi.tex").read_text()
    assert "ref (reference, not ranked) & 99.0 & 99.0" in tex and r"\textbf{70.0}" in tex
    # the authors' Table 1 (no `own`): the published bold, the reference included
    xi_figure.write_tables(xi, "Day-EXTRASUNNY", tmp_path, stem="authors")
    assert "| ref | **99.0** | **99.0** |" in (tmp_path / "authors.md").read_text()
