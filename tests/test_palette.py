"""The detection figures' palette: one colour per model, a hue per family that scales past 20 models, the same
colour for a model in every figure, whichever subset a figure draws."""
from __future__ import annotations

import colorsys
import itertools
import random
from types import SimpleNamespace

import pandas as pd

from pairedgta.figures import det_objects, det_robustness
from pairedgta.figures.palette import FAMILY_HUES, detector_colors, detector_label, zoo_families

FAMILIES = ("fcos", "retinanet", "fasterrcnn")
FAKE = {f"user_{family}_{i:02d}": family for family in FAMILIES for i in range(8)}  # 24 models without a config


def _rgb(color: str) -> tuple[float, float, float]:
    return tuple(int(color[k:k + 2], 16) / 255 for k in (1, 3, 5))


def test_24_models_over_3_families_get_distinct_colours_in_their_family_s_hue():
    colors = detector_colors(FAKE, families=FAKE)
    assert set(colors) == set(FAKE) and len(set(colors.values())) == len(FAKE)
    # distinct to the eye, not only as strings: every pair differs by a visible step in RGB
    closest = min(sum((x - y) ** 2 for x, y in zip(_rgb(a), _rgb(b))) ** 0.5
                  for a, b in itertools.combinations(colors.values(), 2))
    assert closest > 0.05, closest
    for name, family in FAKE.items():
        hue = colorsys.rgb_to_hls(*_rgb(colors[name]))[0]
        assert abs(hue - FAMILY_HUES[family]) < 0.03, (name, hue)  # the family's hue, shades within it
    assert detector_label("user_fcos_00", FAKE).endswith("(FCOS)")  # the legend says which family


def test_a_model_s_colour_does_not_depend_on_order_or_on_the_other_models_drawn():
    names = list(FAKE)
    shuffled = random.Random(0).sample(names, len(names))
    assert detector_colors(names, FAKE) == detector_colors(shuffled, FAKE)
    zoo = sorted(zoo_families())
    assert len(zoo) >= 8 and len(set(detector_colors(zoo).values())) == len(zoo)
    whole = detector_colors(zoo)
    for name in zoo:  # a figure of one member, or of a few, draws it as the figure of all of them does
        assert detector_colors([name]) == {name: whole[name]}
    assert detector_colors(zoo[::2]) == {n: whole[n] for n in zoo[::2]}


def _evaluation(model: str, k: int):
    conds = ["Day-EXTRASUNNY", "Night-EXTRASUNNY"]
    ap = pd.DataFrame({"model": model, "condition": conds, "class_name": "all", "ap": [0.5, 0.1 * k]})
    rob = pd.DataFrame({"model": [model], "metric": ["ap"], "conditions": ["*"], "rPC": [0.3]})
    found = pd.DataFrame({"model": model, "class_name": "all", "variable": "height", "condition": "Night-EXTRASUNNY",
                          "found": [0.2, 0.6], "objects": [10, 5], "bin_low": [8, 32]})
    return SimpleNamespace(model=model, gt_ap=lambda: ap, robustness=lambda: rob, objects_found=lambda: found)


def test_the_same_model_has_the_same_colour_in_two_figures(tmp_path, monkeypatch):
    from matplotlib.colors import to_hex

    members = sorted(zoo_families())
    drawn = {}
    for module in (det_robustness, det_objects):
        figures = []
        monkeypatch.setattr(module, "save", lambda fig, *a, figures=figures: figures.append(fig) or [])
        # each figure draws another subset (the robustness figure all members, the objects figure every other one)
        models = members if module is det_robustness else members[::2]
        p = SimpleNamespace(evaluations=[_evaluation(m, k) for k, m in enumerate(models)], label="",
                            grid=SimpleNamespace(reference="Day-EXTRASUNNY"))
        opts = SimpleNamespace(stem=lambda name, label: name, formats=["png"], dpi=40)
        module.draw([p], tmp_path, opts)
        (fig,) = figures
        drawn[module.__name__] = {line.get_label(): to_hex(line.get_color()) for line in fig.axes[0].get_lines()}
    robustness, objects = drawn.values()
    assert len(set(robustness.values())) == len(members)  # no two detectors share a colour (three shared a grey)
    assert objects and all(robustness[label] == color for label, color in objects.items())
    assert all(label.endswith(("(FCOS)", "(RetinaNet)", "(Faster R-CNN)")) for label in robustness)
