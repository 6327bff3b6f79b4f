"""The run's configuration as typed, frozen nodes: one dataclass per node the run reads, one default and one check
per key, next to each other. The YAML under pairedgta/conf stays what users read and override; the defaults here
mirror it and tests/test_schema.py asserts they agree key by key. `parse` is the one reader of the composed
container: below the entry, stages and figures receive these objects, never the raw dict.

The group nodes whose keys depend on the chosen option (renderer, region, camera, dataset, conditions, model) stay
mappings here: their builders check their own keys (pairedgta/registry.py) with the option at hand."""
from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Optional

from pairedgta import stage_registry, tasks
from pairedgta.errors import ConfigError

MISSING = "???"


def key(default: Any = None, *, ok: Callable[[Any], bool] | None = None, use: str = "fix the value",
        choices: tuple[str, ...] | None = None) -> Any:
    """A config key: its default, what makes a value valid and the one-line advice when it is not."""
    meta = {"ok": ok, "use": use, "choices": choices}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


def node(cls: type) -> Any:
    """A nested node with every key at its default."""
    return field(default_factory=cls, metadata={"node": True})


# --- the nodes -----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CacheConfig:
    verify: str = key("stat", choices=("stat", "content"),
                      use="use stat (trust size + mtime, the default) or content (re-hash every file on every hit)")


@dataclass(frozen=True)
class TrackingConfig:
    uri: str = key("sqlite:///outputs/mlflow.db", use="use an MLflow tracking URI, e.g. sqlite:///outputs/mlflow.db")
    enabled: bool = key(True)
    experiment_name: str = key("default")  # pairedgta/conf/config.yaml: ${name}
    background: bool = key(True)
    class_metrics: bool = key(False)


@dataclass(frozen=True)
class ValidationConfig:
    enabled: bool = key(True)
    structure_threshold: float = key(0.3, ok=lambda v: 0.0 <= v <= 1.0,
                                     use="use a structure agreement in [0, 1] (default 0.3): above 1 every scene fails "
                                         "validation")


@dataclass(frozen=True)
class PairingConfig:
    camera_jitter_m: float = key(0.0, ok=lambda v: v >= 0, use="use metres >= 0 (0 = perfect pairing)")
    camera_jitter_deg: float = key(0.0, ok=lambda v: v >= 0, use="use degrees >= 0 (0 = perfect pairing)")
    object_resample_prob: float = key(0.0, ok=lambda v: 0.0 <= v <= 1.0, use="use a probability in [0, 1]")
    object_move_m: float = key(0.0, ok=lambda v: v >= 0, use="use metres >= 0 (0 = perfect pairing)")


@dataclass(frozen=True)
class CameraPoseConfig:
    x: float = key(0.0)
    y: float = key(0.5)
    z: float = key(1.6)
    rot_x: float = key(0.0)
    rot_y: float = key(0.0)
    rot_z: float = key(0.0)
    fov: float = key(60.0, ok=lambda v: 0.0 < v < 180.0,
                     use="use a horizontal field of view in degrees, 0 < fov < 180 (the paper's camera: 60)")


@dataclass(frozen=True)
class ObjectsConfig:
    min: int = key(0, ok=lambda v: v >= 0, use="use a number of dynamic objects >= 0")
    max: int = key(3, ok=lambda v: v >= 0, use="use a number of dynamic objects >= 0")
    d_min: float = key(4.0, ok=lambda v: v >= 0, use="use a minimum distance between objects in metres >= 0")
    forward_range: list[float] = key([6.0, 30.0], ok=lambda v: len(v) == 2 and v[0] <= v[1],
                                     use="use [near, far] in metres, near <= far")
    lateral_range: list[float] = key([-6.0, 6.0], ok=lambda v: len(v) == 2 and v[0] <= v[1],
                                     use="use [left, right] in metres, left <= right")


@dataclass(frozen=True)
class Endpoint:
    host: str = key("127.0.0.1")
    port: int = key(8000, ok=lambda v: 0 < v < 65536, use="use a TCP port 1..65535")


def _shards(num: int, shard: int, where: str) -> None:
    if num < 1:
        raise ConfigError(f"{where}.num_shards={num}; set it to at least 1")
    if not 0 <= shard < num:
        raise ConfigError(f"{where}.shard={shard} is outside 0..{num - 1} ({where}.num_shards={num})")


@dataclass(frozen=True)
class GenerateConfig:
    num_scenes: int = key(8, ok=lambda v: 1 <= v <= 10_000_000, use="use an integer from 1 to 10,000,000")
    seed: int = key(0, use="use an integer")
    workers: int = key(1, ok=lambda v: v >= 1, use="use an integer >= 1")
    endpoints: list[Endpoint] = key([])
    num_shards: int = key(1, use="use a whole number >= 1")
    shard: int = key(0, use="use a whole number")
    drop_invalid: bool = key(True)
    validation: ValidationConfig = node(ValidationConfig)
    pairing: PairingConfig = node(PairingConfig)
    camera: CameraPoseConfig = node(CameraPoseConfig)
    objects: ObjectsConfig = node(ObjectsConfig)

    def check(self, where: str) -> None:
        _shards(self.num_shards, self.shard, f"{where}generate")
        if self.objects.min > self.objects.max:
            raise ConfigError(f"{where}generate.objects.min={self.objects.min} is above generate.objects.max="
                              f"{self.objects.max}; set min <= max")


@dataclass(frozen=True)
class PseudolabelConfig:
    tau: float = key(0.6, ok=lambda v: 0.0 <= v <= 1.0, use="use a softmax threshold in [0, 1]")
    batch_size: int = key(4, ok=lambda v: v >= 1, use="use an integer >= 1")


SAMPLINGS = ("all", "random_one")


def _workers(value: Any) -> bool:
    return value in (None, "auto") or (isinstance(value, int) and not isinstance(value, bool) and value >= 0)


@dataclass(frozen=True)
class EvaluateConfig:
    batch_size: int = key(4, ok=lambda v: v >= 1, use="use an integer >= 1")
    conditions: Optional[list[str]] = key(None)
    sampling: str = key("all", choices=SAMPLINGS,
                        use="all = every adverse condition per group, random_one = one drawn per group, the authors' "
                            "loader")
    sampling_seed: int = key(0, use="use an integer")
    num_workers: Any = key("auto", ok=_workers,
                           use="use auto or a number of decoding processes >= 0 (0 = decode in the main process)")
    num_shards: int = key(1, use="use a whole number >= 1")
    shard: int = key(0, use="use a whole number")

    def check(self, where: str) -> None:
        _shards(self.num_shards, self.shard, f"{where}evaluate")

    def decode_workers(self, device: str) -> int:
        """DataLoader processes: auto = none on the CPU (the forward pass is the bottleneck); on a GPU all cores
        but two (the main process, the pinning thread), at most 16: a 2048x1024 PNG takes a core ~30 ms to decode,
        and a fast model in bf16 evaluates hundreds of images a second."""
        if self.num_workers not in (None, "auto"):
            return int(self.num_workers)
        import os

        return 0 if device == "cpu" else max(1, min(16, (os.cpu_count() or 1) - 2))


@dataclass(frozen=True)
class RankingPlotConfig:
    condition: Optional[str] = key(None)
    classes: list[str] = key(["person", "car"])
    window: int = key(5, ok=lambda v: v >= 1, use="use an integer >= 1")


@dataclass(frozen=True)
class RobustnessPlotConfig:
    classes: Optional[list[str]] = key(None)
    break_below: float = key(0.5, ok=lambda v: 0.0 < v <= 1.0,
                             use="use a mean-xi level in (0, 1]: the breaking point is the first ladder step below it "
                                 "(default 0.5)")


@dataclass(frozen=True)
class AblationPlotConfig:
    selection: Optional[str] = key(None)  # null: the first of metric.rho.selections


@dataclass(frozen=True)
class TableFilterConfig:
    reference_model: Optional[str] = key(None)
    metric_type: Optional[str] = key(None)
    conf_threshold: Optional[float] = key(None, use="use the confidence threshold as the CSV writes it, e.g. 0.6")


@dataclass(frozen=True)
class PlotConfig:
    formats: list[str] = key(["png", "pdf"])
    dpi: float = key(150, ok=lambda v: v > 0, use="use dots per inch > 0, e.g. 150")
    figures: list[str] = key(["xi_models", "xi_table", "ranking", "qualitative", "contact_sheet", "robustness"])
    qualitative_groups: int = key(2, ok=lambda v: v >= 0, use="use an integer >= 0")
    qualitative_conditions: Optional[list[str]] = key(None)
    distribution_example: Optional[str] = key(None)
    collect_cached: bool = key(False)
    table_csv: Optional[str] = key(None)
    frame_counts_csv: Optional[str] = key(None)
    table_filter: TableFilterConfig = node(TableFilterConfig)
    robustness: RobustnessPlotConfig = node(RobustnessPlotConfig)
    ranking: RankingPlotConfig = node(RankingPlotConfig)
    ablation: AblationPlotConfig = node(AblationPlotConfig)

    def check(self, where: str) -> None:
        from matplotlib.backend_bases import FigureCanvasBase

        supported = FigureCanvasBase.get_supported_filetypes()
        bad = [f for f in self.formats if str(f).lower() not in supported]
        if bad or not self.formats:
            raise ConfigError(f"{where}plot.formats={self.formats}: unknown format(s) {bad}; matplotlib writes "
                              f"{', '.join(sorted(supported))}")


@dataclass(frozen=True)
class RhoConfig:
    m: int = key(25, ok=lambda v: v >= 1, use="use an integer >= 1")
    selections: list[str] = key(["top_m", "nonzero"])
    headline: Optional[str] = key("top_m")
    classes: Optional[list[str]] = key(None)
    clean_condition: Optional[str] = key(None)
    min_frames: int = key(10, ok=lambda v: v >= 0, use="use an integer >= 0 (0 = any number of frames)")


@dataclass(frozen=True)
class BootstrapConfig:
    resamples: int = key(1000, ok=lambda v: v >= 0, use="use an integer >= 0 (0 = no intervals)")
    confidence: float = key(0.95, ok=lambda v: 0.0 < v < 1.0, use="use a level strictly between 0 and 1, e.g. 0.95")
    seed: int = key(0, use="use an integer")


@dataclass(frozen=True)
class ValidityConfig:
    permutations: int = key(10000, ok=lambda v: v >= 0, use="use an integer >= 0 (0 = no permutation p-value)")
    rpc_min_clean_miou: float = key(0.1, ok=lambda v: 0.0 <= v < 1.0,
                                    use="use a clean mIoU in [0, 1): below it rPC is undefined (0 = no floor)")
    twins: list[list[str]] = key([], ok=lambda v: all(isinstance(p, list) and len(p) == 2 and p[0] != p[1]
                                                      and all(isinstance(x, str) for x in p) for p in v),
                                 use="use a list of [model, its twin] pairs: two runs of one recipe differing in the "
                                     "seed only (GDE), e.g. [[demo_ddrnet_short, demo_ddrnet_short_seed1]]")


REFERENCE_SOURCES = ("pseudo_label", "ground_truth", "both")


@dataclass(frozen=True)
class MetricConfig:
    """The metric convention (pairedgta/conf/metric/<name>.yaml; the defaults are metric=strict's)."""
    convention: str = key("strict")
    absent: str = key("nan")
    min_images: int = key(3)
    min_pixels: int = key(1000)
    mean_exclude: list[str] = key([])
    agreement: str = key("pooled")
    min_transmittance: float = key(0.0, ok=lambda v: 0.0 <= v < 1.0,
                                   use="use a transmittance in [0, 1): 0 scores every pixel (the paper), e.g. 0.05 "
                                       "leaves out what the air hides")
    tau_mass: float = key(0.9, ok=lambda v: 0.0 <= v <= 1.0, use="use a threshold in [0, 1]")
    rho: RhoConfig = node(RhoConfig)
    bootstrap: BootstrapConfig = node(BootstrapConfig)
    validity: ValidityConfig = node(ValidityConfig)
    reference: str = key("both", choices=REFERENCE_SOURCES)

    def check(self, where: str) -> None:
        from pairedgta.metrics.conventions import convention_from_config

        try:  # the convention's own parser: absent, mean_exclude, agreement, selections, headline, support
            convention_from_config(dataclasses.asdict(self))
        except ConfigError as exc:
            raise ConfigError(f"{where}{exc}") from None


@dataclass(frozen=True)
class CostConfig:
    csv: Optional[str] = key(None)
    label: Optional[str] = key(None)
    paper: bool = key(True)
    paper_label: Optional[str] = key(None)


@dataclass(frozen=True)
class ReportConfig:
    """The model_report figure (+experiment=model_report): the chosen `model` placed against a population."""
    population: Optional[list[str]] = key(None, ok=lambda v: len(v) >= 1 and len(v) == len(set(v)),
                                          use="use a list of model names without repeats, e.g. "
                                              "report.population=[demo_ddrnet,demo_pidnet] (null = the offline zoo)")
    worst_conditions: int = key(3, ok=lambda v: v >= 1, use="use a number of conditions >= 1")
    worst_cases: int = key(4, ok=lambda v: v >= 0, use="use a number of images >= 0 (0 = no qualitative cases)")


@dataclass(frozen=True)
class DetectionConfig:
    """task=detection: box matching and the ground truth's rules (pairedgta/detection/boxes.py)."""
    iou: float = key(0.5, ok=lambda v: 0.0 < v < 1.0, use="use an IoU strictly between 0 and 1, e.g. 0.5")
    min_area: int = key(100, ok=lambda v: v >= 0, use="use a number of visible pixels >= 0 (Cityscapes: 100)")
    min_boxes: int = key(5, ok=lambda v: v >= 1, use="use a number of reference boxes >= 1")
    max_detections: int = key(100, ok=lambda v: v >= 1, use="use a number of boxes per image >= 1 (COCO: 100)")
    estimators: bool = key(False)  # also BoS and the pre-NMS consistency per image (two more forwards an image)


@dataclass(frozen=True)
class RunConfig:
    """The composed config of one run (or of one pass of a run with `variants`)."""
    name: str = key("default")
    task: str = key(tasks.DEFAULT, choices=tasks.NAMES)
    models: Optional[list[str]] = key(["demo_segformer", "demo_segformer_noaug", "demo_ddrnet", "demo_pidnet"])
    reference_model: Optional[str] = key("demo_segformer")  # null: the `model` group's
    model_overrides: dict[str, Any] = key({})
    per_task: dict[str, Any] = key({})  # an experiment's settings per task (models: ${per_task.${task}.models})
    variants: Optional[list[Any]] = key(None)
    stages: list[str] = key(stage_registry.graph())  # every stage of pairedgta/stage_registry.py but the checks
    force: list[str] = key([])
    cache_dir: str = key("outputs/cache")
    cache: CacheConfig = node(CacheConfig)
    device: str = key("cpu")
    threads: int = key(2, ok=lambda v: v >= 1, use="use the number of CPU threads for inference, >= 1")
    seed: int = key(0, use="use an integer")
    tracking: TrackingConfig = node(TrackingConfig)
    generate: GenerateConfig = node(GenerateConfig)
    pseudolabel: PseudolabelConfig = node(PseudolabelConfig)
    evaluate: EvaluateConfig = node(EvaluateConfig)
    plot: PlotConfig = node(PlotConfig)
    metric: MetricConfig = node(MetricConfig)
    cost: CostConfig = node(CostConfig)
    report: ReportConfig = node(ReportConfig)
    detection: DetectionConfig = node(DetectionConfig)
    photometry: dict[str, Any] = key({})  # bands and limits of the photometry figure (its defaults live there)
    # the chosen group options: checked by their builders, which know the option's keys
    conditions: dict[str, Any] = key({})
    region: dict[str, Any] = key({})
    renderer: dict[str, Any] = key({})
    camera: dict[str, Any] = key({})
    model: dict[str, Any] = key({})
    dataset: dict[str, Any] = key({})
    acdc: dict[str, Any] = key({})  # a second dataset node that variants refer to (experiment=night_vs_acdc)

    def check(self, where: str) -> None:
        known = stage_registry.names()
        if not self.stages:
            figures = ",".join(s.name for s in stage_registry.in_scope("run"))
            raise ConfigError(f"stages=[] runs nothing; list the stages to run, e.g. "
                              f"stages=[{','.join(stage_registry.graph())}] (the default) or stages=[{figures}]")
        for name, values in (("stages", self.stages), ("force", self.force)):
            bad = [s for s in values if s not in known]
            if bad:
                raise ConfigError(f"{name}={bad} names unknown stage(s); stages are {', '.join(known)}")
        check = next((s for s in self.stages if stage_registry.spec(s).scope == "check"), None)
        if check and len(self.stages) > 1:
            raise ConfigError(f"stages={self.stages}: {check} is a model check of its own; run it alone "
                              f"(stages=[{check}])")


def __getattr__(name: str) -> Any:
    """`schema.STAGES`: the stage names of pairedgta/stage_registry.py, read when asked (a spec added there is seen)."""
    if name == "STAGES":
        return stage_registry.names()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


GROUP_NODES = ("conditions", "region", "renderer", "camera", "model", "dataset")
IGNORED = ("hydra", "experiment")  # Hydra's own node; an experiment's name when listed as a key


# --- parsing -------------------------------------------------------------------------------------------------

def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _optional(tp: Any) -> tuple[bool, Any]:
    args = typing.get_args(tp)
    if typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in args:
        rest = [a for a in args if a is not type(None)]
        return True, rest[0]
    return False, tp


def number(value: Any, kind: type, path: str, use: str) -> float | int:
    """`value` as int/float: numeric strings convert; bool, other strings and non-finite numbers are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        if isinstance(value, str):
            try:
                return number(int(value) if kind is int else float(value), kind, path, use)
            except ValueError:
                pass
        raise ConfigError(f"{path}={value!r} is not a number; {use}")
    if kind is int:
        if isinstance(value, float) and not value.is_integer():
            raise ConfigError(f"{path}={value!r} must be an integer; {use}")
        return int(value)
    if not math.isfinite(float(value)):
        raise ConfigError(f"{path}={value!r} must be finite; {use}")
    return float(value)


def _value(tp: Any, value: Any, path: str, use: str) -> Any:
    optional, tp = _optional(tp)
    if value is None or value == MISSING:
        if optional or tp is Any:
            return None
        raise ConfigError(f"{path} is not set; {use}")
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _node(tp, value, path)
    if tp is Any:
        return value
    if tp is bool:
        if isinstance(value, bool):
            return value
        if str(value).lower() in ("true", "false"):
            return str(value).lower() == "true"
        raise ConfigError(f"{path}={value!r} must be true or false")
    if tp in (int, float):
        return number(value, tp, path, use)
    if tp is str:
        if isinstance(value, (dict, list)):
            raise ConfigError(f"{path}={value!r} must be a single value; {use}")
        return str(value)
    if origin is list:
        (item,) = typing.get_args(tp)
        listed = [value] if isinstance(value, (str, int, float)) and item is str else value
        if not isinstance(listed, (list, tuple)):
            raise ConfigError(f"{path}={value!r} must be a list, e.g. {path}=[a,b]")
        return [_value(item, v, f"{path}[{i}]", use) for i, v in enumerate(listed)]
    if origin is dict:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{path}={value!r} must be a mapping")
        return dict(value)
    raise TypeError(f"schema type {tp!r} of {path}")  # a programming error in this module


def _node(cls: type, raw: Any, path: str) -> Any:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{path}={raw!r} must be a mapping with the keys {', '.join(f.name for f in dataclasses.fields(cls))}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in raw if k not in fields and not (cls is RunConfig and k in IGNORED)]
    if unknown:
        close = difflib.get_close_matches(str(unknown[0]), list(fields), n=1, cutoff=0.6)
        prefix = f"{path}." if path else ""
        hint = f"did you mean {prefix}{close[0]}?" if close else f"its keys are {', '.join(fields)}"
        raise ConfigError(f"{prefix}{unknown[0]} is not a key of {path or 'pairedgta'}; {hint}")
    hints = _hints(cls)
    values: dict[str, Any] = {}
    for name, f in fields.items():
        full = f"{path}.{name}" if path else name
        if name not in raw:
            continue
        meta = f.metadata
        value = _value(hints[name], raw[name], full, meta.get("use", "fix the value"))
        if value is not None and meta.get("choices") and value not in meta["choices"]:
            use = meta["use"] if meta["use"].startswith("use ") else f"use one of {', '.join(meta['choices'])}" + (
                f" ({meta['use']})" if meta["use"] != "fix the value" else "")
            raise ConfigError(f"{full}={value!r}; {use}")
        ok = meta.get("ok")
        if value is not None and ok is not None and not ok(value):
            raise ConfigError(f"{full}={raw[name]!r} is out of range; {meta['use']}")
        values[name] = value
    return cls(**values)


def parse(container: Mapping[str, Any], where: str = "") -> RunConfig:
    """The typed config of a composed run config; one ConfigError naming the first bad key. `where`: the prefix
    of a variant's keys in messages (variants[1].)."""
    try:
        run = _node(RunConfig, container, "")
        for part in (run, run.generate, run.evaluate, run.plot, run.metric):
            part.check(where)
    except ConfigError as exc:
        message = str(exc)
        raise ConfigError(message if not where or message.startswith(where) else f"{where}{message}") from None
    return run


def defaults() -> RunConfig:
    """Every key at its schema default (what tests/test_schema.py compares with pairedgta/conf)."""
    return RunConfig()


def as_dict(obj: Any) -> Any:
    """A node as plain data (lists and dicts), e.g. for a stage's hash or an MLflow parameter."""
    return dataclasses.asdict(obj) if dataclasses.is_dataclass(obj) else obj
