"""What runs are called and tagged, so that the MLflow UI lines them up: `<experiment> · <model(s)> ·
<dataset>@<hash>` run names, one upload name per stage result, the xi table's columns and each model's
figure colour. Pure functions: the app names its runs with them whichever Recorder logs them."""
from __future__ import annotations

import re
from typing import Any

TAG = "pairedgta."
SWEEP_TAG = f"{TAG}sweep"  # search: tags.`pairedgta.sweep` = '<sweep folder name>' (parent and model runs)
RUN_COLOR_TAG = "mlflow.runColor"  # the MLflow UI draws a run in this colour instead of one hashed from its id


def run_name(experiment: str, models: list[str], datasets: list[str]) -> str:
    """`smoke · tiny_segformer, tiny_mask2former · generated@1a2b3c4d`: what ran, with what, on what."""
    return " \u00b7 ".join([experiment, ", ".join(models) or "-", ", ".join(datasets) or "-"])[:240]


def bundle(stage: str, key: str, *parts: str) -> str:
    """The name of one upload of a stage's files (`evaluate.<hash>`, `plot.<hash>.<pass>.<model>`), as
    MLflow tag keys allow it."""
    return ".".join([stage, key, *(re.sub(r"[^A-Za-z0-9_\-]+", "_", str(x)) for x in parts)])


def dataset_label(name: str, key: str | None) -> str:
    """A dataset as runs name it: its name and the first 8 characters of its hash (generate or content)."""
    return f"{name}@{str(key).split(':', 1)[-1][:8]}" if key else name


def model_run_color(model: str) -> str:
    """The colour every figure gives `model` (`figures.common.model_color`), as the hex the MLflow UI reads
    from a run's RUN_COLOR_TAG. Without it the UI hashes each run id into 29 colours, so 4 model runs
    share one about one time in five."""
    from pairedgta.figures.model_colors import model_color_hex

    return model_color_hex(model)


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """Nested mappings as dotted keys (MLflow parameters); a list is one JSON value."""
    from pairedgta.jsonio import dumps

    out: dict[str, Any] = {}
    if isinstance(d, dict):
        for k, v in d.items():
            out.update(flatten(v, f"{prefix}{k}."))
    elif isinstance(d, (list, tuple)):
        out[prefix.rstrip(".")] = dumps(d)
    else:
        out[prefix.rstrip(".")] = d
    return out


def clean_metric_name(name: str) -> str:
    """What MLflow accepts in a metric key: anything else becomes `_`."""
    return "".join(ch if ch.isalnum() or ch in "_-./ " else "_" for ch in name)
