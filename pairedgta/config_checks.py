"""Every config value a run reads, checked before any stage runs: a bad value is one ConfigError naming
the key, its value and what to use, not a traceback hours later (after generation) or a silently wrong
result (all-NaN intervals, an ignored condition name). Checks that need files (dataset roots, weights)
stay with the code that opens them; these only need the config.

With `variants`, every pass's config (the run's config with the variant's overrides) is checked too,
and the error names the variant's key."""
from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any, Callable

from pairedgta.configs import merge_variant
from pairedgta.errors import ConfigError

MISSING = "???"


def _get(cfg: dict[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _number(value: Any, key: str, kind: type, where: str) -> float | int:
    """`value` as int/float; bool, strings and non-finite numbers are refused."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        if isinstance(value, str):
            try:
                value = int(value) if kind is int else float(value)
            except ValueError:
                raise ConfigError(f"{where}{key}={value!r} is not a number; {_hint(key)}") from None
        else:
            raise ConfigError(f"{where}{key}={value!r} is not a number; {_hint(key)}")
    if kind is int:
        if isinstance(value, float) and not value.is_integer():
            raise ConfigError(f"{where}{key}={value!r} must be an integer; {_hint(key)}")
        return int(value)
    if not math.isfinite(float(value)):
        raise ConfigError(f"{where}{key}={value!r} must be finite; {_hint(key)}")
    return float(value)


# key -> (type, predicate, what to use)
_HINTS: dict[str, str] = {}


def _rule(key: str, kind: type, ok: Callable[[float], bool], use: str, optional: bool = True) -> tuple:
    _HINTS[key] = use
    return key, kind, ok, use, optional


def _hint(key: str) -> str:
    return _HINTS.get(key, "fix the value")


RULES = [
    _rule("renderer.width", int, lambda v: v > 0, "use a width in pixels >= 1", optional=False),
    _rule("renderer.height", int, lambda v: v > 0, "use a height in pixels >= 1", optional=False),
    _rule("renderer.timeout_s", float, lambda v: v > 0, "use seconds > 0"),
    _rule("renderer.retries", int, lambda v: v >= 0, "use an integer >= 0"),
    _rule("renderer.backoff_s", float, lambda v: v >= 0, "use seconds >= 0"),
    _rule("generate.num_scenes", int, lambda v: 1 <= v <= 10_000_000, "use an integer from 1 to 10,000,000",
          optional=False),
    _rule("generate.camera.fov", float, lambda v: 0.0 < v < 180.0,
          "use a horizontal field of view in degrees, 0 < fov < 180 (the paper's camera: 60)"),
    _rule("renderer.max_distance", float, lambda v: v > 0, "use metres > 0 (how far the street is traced; default 150)"),
    _rule("renderer.noise_std", float, lambda v: v >= 0, "use a standard deviation >= 0 (0 = no sensor noise)"),
    _rule("generate.workers", int, lambda v: v >= 1, "use an integer >= 1"),
    _rule("generate.seed", int, lambda v: True, "use an integer"),
    _rule("pseudolabel.tau", float, lambda v: 0.0 <= v <= 1.0, "use a softmax threshold in [0, 1]", optional=False),
    _rule("pseudolabel.batch_size", int, lambda v: v >= 1, "use an integer >= 1"),
    _rule("evaluate.batch_size", int, lambda v: v >= 1, "use an integer >= 1"),
    _rule("threads", int, lambda v: v >= 1, "use the number of CPU threads for inference, >= 1"),
    _rule("evaluate.sampling_seed", int, lambda v: True, "use an integer"),
    _rule("metric.tau_mass", float, lambda v: 0.0 <= v <= 1.0, "use a threshold in [0, 1]"),
    _rule("metric.min_transmittance", float, lambda v: 0.0 <= v < 1.0,
          "use a transmittance in [0, 1): 0 scores every pixel (the paper), e.g. 0.05 leaves out what the air hides"),
    _rule("metric.rho.m", int, lambda v: v >= 1, "use an integer >= 1"),
    _rule("metric.bootstrap.resamples", int, lambda v: v >= 0, "use an integer >= 0 (0 = no intervals)"),
    _rule("metric.bootstrap.confidence", float, lambda v: 0.0 < v < 1.0, "use a level strictly between 0 and 1, e.g. 0.95"),
    _rule("metric.bootstrap.seed", int, lambda v: True, "use an integer"),
    _rule("metric.validity.permutations", int, lambda v: v >= 0, "use an integer >= 0 (0 = no permutation p-value)"),
    _rule("plot.dpi", float, lambda v: v > 0, "use dots per inch > 0, e.g. 150"),
    _rule("plot.qualitative_groups", int, lambda v: v >= 0, "use an integer >= 0"),
    _rule("plot.ranking.window", int, lambda v: v >= 1, "use an integer >= 1"),
    _rule("plot.robustness.break_below", float, lambda v: 0.0 < v <= 1.0,
          "use a mean-xi level in (0, 1]: the breaking point is the first ladder step below it (default 0.5)"),
    _rule("generate.validation.structure_threshold", float, lambda v: 0.0 <= v <= 1.0,
          "use a structure agreement in [0, 1] (default 0.3): above 1 every scene fails validation"),
    _rule("generate.objects.min", int, lambda v: v >= 0, "use a number of dynamic objects >= 0"),
    _rule("generate.objects.max", int, lambda v: v >= 0, "use a number of dynamic objects >= 0"),
    _rule("generate.objects.d_min", float, lambda v: v >= 0, "use a minimum distance between objects in metres >= 0"),
]


def check_cache_dir(value: Any) -> None:
    """cache_dir must be (or be creatable as) a writable directory on a real file system."""
    if value in (None, "", MISSING):
        raise ConfigError("cache_dir is empty; set cache_dir=PATH (a writable directory)")
    path = Path(str(value)).expanduser().absolute()
    resolved = path.resolve()
    for pseudo in ("/proc", "/sys", "/dev"):
        if resolved == Path(pseudo) or Path(pseudo) in resolved.parents:
            raise ConfigError(f"cache_dir={value} is under {pseudo}, a kernel pseudo file system; use a normal directory")
    existing = path
    while not existing.exists():
        existing = existing.parent
    if existing != path and not existing.is_dir():
        raise ConfigError(f"cache_dir={value}: {existing} is a file, not a directory; use another path")
    if path.exists() and not path.is_dir():
        raise ConfigError(f"cache_dir={value} is a file, not a directory; use another path")
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write-test-"):
            pass
    except OSError as exc:
        raise ConfigError(f"cache_dir={value} is not writable ({exc.strerror or exc}); use a writable directory") from None
    for stage in CACHE_STAGES:  # each stage keeps its entries in a folder of its name
        if (path / stage).exists() and not (path / stage).is_dir():
            raise ConfigError(f"cache_dir={value}: {path / stage} is a file, but the {stage} stage keeps its results in a "
                              "folder of that name; move the file away or use another cache_dir")


CACHE_STAGES = ("generate", "pseudolabel", "evaluate", "plot", "cityscapes_val")


def passes(cfg: dict[str, Any]) -> list[tuple[str, dict[str, Any]]]:
    """(prefix for error messages, config) of the run and of every variant."""
    out = [("", cfg)]
    for i, v in enumerate(cfg.get("variants") or []):
        if isinstance(v, dict):
            v = {k: x for k, x in v.items() if k != "label"}
            out.append((f"variants[{i}].", merge_variant(cfg, v)))
    return out


def condition_names(cfg: dict[str, Any]) -> list[str]:
    """Conditions a pass can show: the grid of `conditions`, or ACDC's own for an ACDC dataset."""
    dataset = cfg.get("dataset") or {}
    if isinstance(dataset, dict) and dataset.get("kind") == "acdc":
        from pairedgta.datasets.acdc import acdc_grid

        return list(acdc_grid(str(dataset.get("condition"))).names)
    from pairedgta.conditions import build_condition_grid

    return list(build_condition_grid(cfg["conditions"]).names)


def _known_model(name: Any, key: str) -> None:
    from pairedgta.models import available_models, model_config

    if not isinstance(name, str) or not name:
        raise ConfigError(f"{key}={name!r}; choose one of: {', '.join(available_models())}")
    try:
        model_config(name)
    except ConfigError as exc:
        raise ConfigError(f"{key}: {exc}") from None


def check_plot(cfg: dict[str, Any], names: set[str], where: str) -> None:
    plot = cfg.get("plot") or {}
    formats = plot.get("formats")
    if formats is not None:
        from matplotlib.backend_bases import FigureCanvasBase

        supported = FigureCanvasBase.get_supported_filetypes()
        listed = [formats] if isinstance(formats, str) else list(formats)
        bad = [f for f in listed if str(f).lower() not in supported]
        if bad or not listed:
            raise ConfigError(f"{where}plot.formats={listed}: unknown format(s) {bad}; matplotlib writes "
                              f"{', '.join(sorted(supported))}")
    wanted = plot.get("qualitative_conditions")
    if wanted is not None:
        listed = [wanted] if isinstance(wanted, str) else list(wanted)
        bad = [c for c in listed if c not in names]
        if bad:
            raise ConfigError(f"{where}plot.qualitative_conditions: unknown condition(s) {bad}; known: {', '.join(sorted(names))}")
    from pairedgta.cityscapes import CLASS_NAMES

    for key, classes in (("plot.ranking.classes", (plot.get("ranking") or {}).get("classes")),
                         ("plot.robustness.classes", (plot.get("robustness") or {}).get("classes")),
                         ("metric.rho.classes", ((cfg.get("metric") or {}).get("rho") or {}).get("classes"))):
        listed = [classes] if isinstance(classes, str) else list(classes or [])
        unknown = [c for c in listed if c not in CLASS_NAMES]
        if unknown:
            raise ConfigError(f"{where}{key}: unknown class(es) {unknown}; use Cityscapes names, e.g. [person, car] "
                              f"(known: {', '.join(CLASS_NAMES)})")
    cond = (plot.get("ranking") or {}).get("condition")
    if cond is not None and cond not in names:
        raise ConfigError(f"{where}plot.ranking.condition={cond!r} is not a condition of this run; known: {', '.join(sorted(names))}")


REFERENCE_SOURCES = ("pseudo_label", "ground_truth", "both")
_HINTS["plot.table_filter.conf_threshold"] = "use the confidence threshold as the CSV writes it, e.g. 0.6"


def check_metric(cfg: dict[str, Any], where: str) -> None:
    """The metric convention (metric.convention, absent, mean_exclude, agreement, rho.selections,
    rho.headline) parsed as the evaluate stage will parse it, and the reference source."""
    metric = cfg.get("metric")
    if not isinstance(metric, dict):
        return
    from pairedgta.metrics.conventions import convention_from_config

    try:
        convention_from_config(metric)
    except ConfigError as exc:
        raise ConfigError(f"{where}{exc}") from None
    if float(metric.get("min_transmittance") or 0.0) > 0.0:
        kind = (cfg.get("dataset") or {}).get("kind")
        backend = (cfg.get("renderer") or {}).get("backend")
        if kind != "generated" or backend == "deepgtav":
            source = f"dataset={kind}" if kind != "generated" else "renderer=deepgtav (GTA V gives no depth)"
            raise ConfigError(f"{where}metric.min_transmittance>0 needs transmittance maps, which {source} does not have; "
                              "set metric.min_transmittance=0 or generate with renderer=blender or synthetic")
    reference = metric.get("reference")
    if reference is not None and reference not in REFERENCE_SOURCES:
        raise ConfigError(f"{where}metric.reference={reference!r}; use one of {', '.join(REFERENCE_SOURCES)}")


def check_evaluate(cfg: dict[str, Any], where: str) -> None:
    from pairedgta.stages.evaluate import SAMPLINGS

    sampling = (cfg.get("evaluate") or {}).get("sampling")
    if sampling is not None and sampling not in SAMPLINGS:
        raise ConfigError(f"{where}evaluate.sampling={sampling!r}; use one of {', '.join(SAMPLINGS)} (all = every adverse "
                          "condition per group, random_one = one drawn per group, the authors' loader)")


def check_stage_keys(cfg: dict[str, Any], names: set[str], where: str) -> None:
    """Keys the stages read and validate themselves, checked with the same code before any stage writes:
    shards, decode workers, condition names, the renderer backend, the objects' range and the camera."""
    from pairedgta.stages.common import shard_keys
    from pairedgta.stages.evaluate import decode_workers

    def again(exc: ConfigError) -> ConfigError:
        return ConfigError(f"{where}{exc}")

    gen, ev = cfg.get("generate") or {}, cfg.get("evaluate") or {}
    try:
        shard_keys(gen, "generate")
        shard_keys(ev, "evaluate")
        decode_workers(ev.get("num_workers"), "cpu")
    except ConfigError as exc:
        raise again(exc) from None
    objects = gen.get("objects") or {}
    if isinstance(objects.get("min"), int) and isinstance(objects.get("max"), int) and objects["min"] > objects["max"]:
        raise ConfigError(f"{where}generate.objects.min={objects['min']} is above generate.objects.max={objects['max']}; "
                          "set min <= max")
    if names:
        unknown = [c for c in (ev.get("conditions") or []) if c not in names]
        if unknown:
            raise ConfigError(f"{where}evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(sorted(names))}")
        clean = ((cfg.get("metric") or {}).get("rho") or {}).get("clean_condition")
        if clean is not None and clean not in names:
            raise ConfigError(f"{where}metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(sorted(names))}")
    exposures = (cfg.get("camera") or {}).get("overrides") or {}
    if exposures and isinstance(cfg.get("conditions"), dict):  # Camera.exposure looks them up by these names
        from pairedgta.conditions import build_condition_grid

        grid = build_condition_grid(cfg["conditions"])
        valid = [*grid.names, *dict.fromkeys(c.time for c in grid)]
        bad = [str(k) for k in exposures if str(k) not in valid]
        if bad:
            raise ConfigError(f"{where}camera.overrides.{bad[0]} is not a condition or time of this run, so no image "
                              f"would use it; use one of {', '.join(valid)}")
    renderer = cfg.get("renderer") or {}
    backend = renderer.get("backend")
    if backend is not None:
        from pairedgta.render import RENDERERS

        if backend not in RENDERERS.names():
            raise ConfigError(f"{where}renderer.backend={backend!r}; use one of {', '.join(RENDERERS.names())} "
                              "(renderer=blender|synthetic|deepgtav)")
        if backend == "blender" and isinstance(renderer.get("camera"), dict):
            from pairedgta.render.camera import Camera

            try:
                Camera.from_cfg(renderer["camera"])
            except ConfigError as exc:
                raise again(exc) from None


def check_table_filter(plot: dict[str, Any], where: str) -> None:
    """plot.table_filter picks rows of the authors' CSV (plot.table_csv) by these columns only."""
    filters = plot.get("table_filter")
    if filters is None:
        return
    from pairedgta.figures.paper_table import FILTERS  # with pyplot, 0.4 s: only when a filter is given

    if not isinstance(filters, dict):
        raise ConfigError(f"{where}plot.table_filter={filters!r} must be a mapping with the keys {', '.join(FILTERS)}")
    unknown = sorted(set(filters) - set(FILTERS))
    if unknown:
        raise ConfigError(f"{where}plot.table_filter: unknown key(s) {', '.join(unknown)}; known keys: {', '.join(FILTERS)}")
    if filters.get("conf_threshold") is not None:
        _number(filters["conf_threshold"], "plot.table_filter.conf_threshold", float, where)


def check_run_config(cfg: dict[str, Any]) -> None:
    """Raise one ConfigError for the first bad value of a resolved run config (see the module doc).
    The first step of every run, so it also starts the run's cache of composed model configs."""
    from pairedgta import configs

    configs.reset_cache()
    check_cache_dir(cfg.get("cache_dir"))
    from pairedgta.cache import VERIFY_MODES

    verify = (cfg.get("cache") or {}).get("verify", "stat")
    if verify not in VERIFY_MODES:
        raise ConfigError(f"cache.verify={verify!r}; use stat (trust size + mtime, the default) or content "
                          "(re-hash every file on every hit)")
    stages = cfg.get("stages")
    if stages is not None and not list(stages):
        raise ConfigError("stages=[] runs nothing; list the stages to run, e.g. stages=[generate,pseudolabel,evaluate,plot] "
                          "(the default) or stages=[plot]")
    configs = passes(cfg)
    names: set[str] = set()
    for where, pcfg in configs:
        names |= set(condition_names(pcfg))
    for where, pcfg in configs:
        for key, kind, ok, use, optional in RULES:
            value = _get(pcfg, key)
            if value is None or value == MISSING:
                if optional or key.split(".")[0] not in pcfg:
                    continue
                raise ConfigError(f"{where}{key} is not set; {use}")
            if not ok(_number(value, key, kind, where)):
                raise ConfigError(f"{where}{key}={value!r} is out of range; {use}")
        _known_model(pcfg.get("reference_model"), f"{where}reference_model")
        check_plot(pcfg, names, where)
        check_table_filter(pcfg.get("plot") or {}, where)
        check_metric(pcfg, where)
        check_evaluate(pcfg, where)
        check_stage_keys(pcfg, set(condition_names(pcfg)), where)
    for i, name in enumerate(cfg.get("models") or []):
        _known_model(name, f"models[{i}]")


# -- keys added on the command line (`+key=value`) -------------------------------------------------
# mappings whose keys are the user's to choose (camera.overrides: condition or time names, checked against the
# run's grid by check_stage_keys)
OPEN_KEYS = ("model_overrides", "variants", "hydra", "camera.overrides")


def open_key(key: str) -> bool:
    return any(key == k or key.startswith(k + ".") for k in OPEN_KEYS)
# nodes whose builder checks its keys itself, naming the keys it reads (pairedgta/registry.py: check_keys)
BUILT_NODES = ("model", "renderer", "region", "dataset")


def _paths(node: Any, prefix: str = "") -> set[str]:
    out: set[str] = set()
    if isinstance(node, dict):
        for k, v in node.items():
            if k == "defaults":
                continue
            key = f"{prefix}{k}"
            out.add(key)
            out |= _paths(v, key + ".")
    return out


def _load_yaml(path: Path) -> Any:
    """A config file's tree (plain YAML: a tenth of OmegaConf.load's time; only its keys are read)."""
    import yaml

    return yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)) or {}


def known_key_paths() -> set[str]:
    """Every dotted key some config file of the package defines: config.yaml and the experiments (global),
    each group option under its group (renderer.noise_std), the groups themselves."""
    from pairedgta.configs import CONFIG_DIR

    known: set[str] = set()
    for path in [CONFIG_DIR / "config.yaml", *sorted((CONFIG_DIR / "experiment").glob("*.yaml"))]:
        known |= _paths(_load_yaml(path))
    for group in (p for p in CONFIG_DIR.iterdir() if p.is_dir() and p.name not in ("experiment", "hydra", "zoo")):
        known.add(group.name)
        for option in group.glob("*.yaml"):
            known |= _paths(_load_yaml(option), f"{group.name}.")
    return known


# config groups whose option file (with the options its defaults list pulls in) names every key their reader
# takes: a key added to one (`+renderer.colour=red`) would fail, or be ignored, only when a stage builds it,
# after generate has written cache entries
CLOSED_GROUPS = ("renderer", "camera", "metric", "region", "dataset")


def group_option_keys(group: str, option: str) -> set[str] | None:
    """The top-level keys of pairedgta/conf/<group>/<option>.yaml and of the options of the same group its
    defaults list names (camera=dashcam starts from camera=gta); None when there is no such option file."""
    from pairedgta.configs import CONFIG_DIR

    path = CONFIG_DIR / group / f"{option}.yaml"
    if not path.is_file():
        return None
    tree = _load_yaml(path)
    keys = {k for k in tree if k != "defaults"}
    for entry in tree.get("defaults") or []:
        if isinstance(entry, str) and entry != "_self_" and entry != option:
            keys |= group_option_keys(group, entry) or set()
    return keys


def experiment_keys(group: str) -> set[str]:
    """Keys the experiments set in `group`'s node beyond its options' (region.town_seeds): read by the code too."""
    from pairedgta.configs import CONFIG_DIR

    keys: set[str] = set()
    for path in sorted((CONFIG_DIR / "experiment").glob("*.yaml")):
        node = _load_yaml(path).get(group)
        keys |= set(node) if isinstance(node, dict) else set()
    return keys


def default_choices() -> dict[str, str]:
    """group -> option as pairedgta/conf/config.yaml's defaults list chooses them."""
    from pairedgta.configs import CONFIG_DIR

    entries = _load_yaml(CONFIG_DIR / "config.yaml").get("defaults") or []
    return {str(k): str(v) for e in entries if isinstance(e, dict) for k, v in e.items()}


def argv_choices(argv: list[str]) -> dict[str, str]:
    """group -> option as Hydra will choose them, read from the command line before it composes:
    config.yaml's defaults, then the experiment's `override /group: option`, then `group=option`."""
    from pairedgta.configs import CONFIG_DIR

    choices = default_choices()
    given = dict(a.lstrip("+").split("=", 1) for a in argv if "=" in a and not a.startswith(("-", "~")))
    experiment = CONFIG_DIR / "experiment" / f"{given.get('experiment')}.yaml"
    for entry in (_load_yaml(experiment).get("defaults") or []) if experiment.is_file() else []:
        for k, v in (entry.items() if isinstance(entry, dict) else ()):
            choices[str(k).removeprefix("override").strip().lstrip("/")] = str(v)
    return {**choices, **{k: v for k, v in given.items() if k in choices}}


def check_group_key(key: str, choices: dict[str, Any] | None) -> None:
    """`key` (e.g. renderer.colour) added to a closed group must be a key of the chosen option's file."""
    from pairedgta.configs import CONFIG_DIR

    group, _, rest = key.partition(".")
    option = (choices or {}).get(group) or default_choices().get(group)
    known = group_option_keys(group, str(option)) if option else None
    child = rest.split(".")[0]
    if known is None or child in known | experiment_keys(group):
        return  # a key inside a known key's mapping (renderer.town.x) is checked by that node's reader
    import difflib

    close = difflib.get_close_matches(child, sorted(known), n=1, cutoff=0.6)
    others = sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml") if child in (group_option_keys(group, p.stem) or ()))
    more = f" and {len(others) - 2} more" if len(others) > 3 else ""
    hint = (f"did you mean {group}.{close[0]}?" if close and not others else f"its keys are {', '.join(sorted(known))}"
            + (f" ({group}.{child} is a key of {group}={', '.join(others[:2] if more else others)}{more})" if others else ""))
    raise ConfigError(f"{group}.{child} is not a key of {group}={option}; {hint}")


def check_added_keys(overrides: list[str], choices: dict[str, Any] | None = None) -> None:
    """A `+key=value` whose key no config reads would be silently ignored, or fail only when a stage builds
    it: one line instead, before any stage runs. `choices`: the run's group options (Hydra's runtime choices;
    config.yaml's defaults when not given), whose files name the keys of the closed groups."""
    for o in overrides:  # `++` adds a key too, where it does not exist yet
        key = o.lstrip("+").split("=", 1)[0].strip()
        if o.startswith("+") and "=" in o and key.split(".")[0] in CLOSED_GROUPS and "." in key:
            check_group_key(key, choices)
    added = [o[1:] for o in overrides if o.startswith("+") and not o.startswith("++") and "=" in o]
    if not added:
        return
    known = None
    for item in added:
        key = item.split("=", 1)[0].strip()
        if open_key(key) or key.split(".")[0] in BUILT_NODES or key.startswith("experiment"):
            continue
        known = known if known is not None else known_key_paths()
        if key not in known:
            from pairedgta.conditions import REPLACED_KEYS

            if key.startswith("conditions.") and key.split(".")[-1] in REPLACED_KEYS:
                raise ConfigError(f"+{key}: {key.split('.')[-1]} is no longer a condition key; use "
                                  f"{REPLACED_KEYS[key.split('.')[-1]]}")
            import difflib

            close = (sorted(k for k in known if k.split(".")[-1] == key.split(".")[-1])[:3]
                     or difflib.get_close_matches(key, sorted(known), n=1, cutoff=0.8))
            hint = f"; did you mean {', '.join(close)}?" if close else "; see python -m pairedgta --cfg job for the keys"
            raise ConfigError(f"+{key}: no part of pairedgta reads this key, so it would be ignored{hint}")
