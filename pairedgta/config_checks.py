"""Every config value a run reads, checked before any stage runs: a bad value is one ConfigError naming
the key, its value and what to use, not a traceback hours later (after generation) or a silently wrong
result (all-NaN intervals, an ignored condition name). Checks that need files (dataset roots, weights)
stay with the code that opens them; these only need the config.

With `variants`, every pass's config (the run's config with the variant's overrides) is checked too,
and the error names the variant's key."""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Callable

from pairedgta import schema, stage_registry
from pairedgta.configs import merge_variant
from pairedgta.errors import ConfigError
from pairedgta.schema import RunConfig

from pairedgta.schema import MISSING


def _get(cfg: dict[str, Any], dotted: str) -> Any:
    node: Any = cfg
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


# key -> (type, predicate, what to use)
_HINTS: dict[str, str] = {}


def _rule(key: str, kind: type, ok: Callable[[float], bool], use: str, optional: bool = True) -> tuple:
    _HINTS[key] = use
    return key, kind, ok, use, optional


def _hint(key: str) -> str:
    return _HINTS.get(key, "fix the value")


# the chosen group options' numeric keys (the run's own nodes are typed in pairedgta/schema.py)
RULES = [
    _rule("renderer.width", int, lambda v: v > 0, "use a width in pixels >= 1", optional=False),
    _rule("renderer.height", int, lambda v: v > 0, "use a height in pixels >= 1", optional=False),
    _rule("renderer.timeout_s", float, lambda v: v > 0, "use seconds > 0"),
    _rule("renderer.retries", int, lambda v: v >= 0, "use an integer >= 0"),
    _rule("renderer.backoff_s", float, lambda v: v >= 0, "use seconds >= 0"),
    _rule("renderer.max_distance", float, lambda v: v > 0, "use metres > 0 (how far the street is traced; default 150)"),
    _rule("renderer.noise_std", float, lambda v: v >= 0, "use a standard deviation >= 0 (0 = no sensor noise)"),
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
    for stage in stage_registry.names():  # each stage keeps its entries in a folder of its name
        if (path / stage).exists() and not (path / stage).is_dir():
            raise ConfigError(f"cache_dir={value}: {path / stage} is a file, but the {stage} stage keeps its results in a "
                              "folder of that name; move the file away or use another cache_dir")


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


def check_plot(run: RunConfig, names: set[str], where: str) -> None:
    """The plot keys that name conditions or classes, which only the run's grid and Cityscapes know."""
    plot = run.plot
    if plot.qualitative_conditions is not None:
        bad = [c for c in plot.qualitative_conditions if c not in names]
        if bad:
            raise ConfigError(f"{where}plot.qualitative_conditions: unknown condition(s) {bad}; known: {', '.join(sorted(names))}")
    from pairedgta.cityscapes import CLASS_NAMES

    for key, classes in (("plot.ranking.classes", plot.ranking.classes), ("plot.robustness.classes", plot.robustness.classes),
                         ("metric.rho.classes", run.metric.rho.classes)):
        unknown = [c for c in classes or [] if c not in CLASS_NAMES]
        if unknown:
            raise ConfigError(f"{where}{key}: unknown class(es) {unknown}; use Cityscapes names, e.g. [person, car] "
                              f"(known: {', '.join(CLASS_NAMES)})")
    cond = plot.ranking.condition
    if cond is not None and cond not in names:
        raise ConfigError(f"{where}plot.ranking.condition={cond!r} is not a condition of this run; known: {', '.join(sorted(names))}")


def check_transmittance(run: RunConfig, where: str) -> None:
    """metric.min_transmittance > 0 needs transmittance maps: rendered by blender and synthetic only."""
    if run.metric.min_transmittance > 0.0:
        kind, backend = run.dataset.get("kind"), run.renderer.get("backend")
        if kind != "generated" or backend == "deepgtav":
            source = f"dataset={kind}" if kind != "generated" else "renderer=deepgtav (GTA V gives no depth)"
            raise ConfigError(f"{where}metric.min_transmittance>0 needs transmittance maps, which {source} does not have; "
                              "set metric.min_transmittance=0 or generate with renderer=blender or synthetic")


def check_corruptions(run: RunConfig, where: str) -> None:
    """Corruption conditions (conditions.corruptions; their names and severities are checked where the grid is
    built): a dataset with a clean condition to corrupt, no transmittance asked of them, the library installed."""
    if not run.conditions or not run.conditions.get("corruptions"):
        return
    from pairedgta import corruptions
    from pairedgta.conditions import build_condition_grid

    grid = build_condition_grid(run.conditions)
    if not grid.corrupted:
        return
    kind = run.dataset.get("kind")
    if kind not in ("generated", "paired_gta"):
        raise ConfigError(f"{where}conditions.corruptions: dataset={kind} has no clean condition of this grid to "
                          "corrupt (ACDC brings its own two conditions, Cityscapes none); use dataset=generated or paired_gta, "
                          "or conditions without corruptions")
    if run.metric.min_transmittance > 0.0:
        raise ConfigError(f"{where}metric.min_transmittance={run.metric.min_transmittance} does not apply to "
                          f"corruption conditions ({grid.corrupted[0].name}, ...: a 2D filter has no depth, so no transmittance); "
                          "set metric.min_transmittance=0, or leave out conditions.corruptions")
    size = [run.renderer.get("width"), run.renderer.get("height")]
    if kind == "generated" and all(isinstance(v, int) for v in size) and min(size) < 32:
        raise ConfigError(f"{where}renderer.width x height = {size[0]}x{size[1]}: the corruptions need images of at "
                          "least 32x32 (imagecorruptions); set renderer.width and renderer.height >= 32")
    if not corruptions.installed():
        raise ConfigError(f"{where}conditions.corruptions needs the package imagecorruptions; install it with "
                          "pip install -e \".[corruptions]\" -c constraints.txt")


def check_stage_keys(run: RunConfig, names: set[str], where: str) -> None:
    """Keys the stages check against the run's grid or a registry, checked before any stage writes: condition
    names, the renderer backend and the camera."""
    if names:
        unknown = [c for c in run.evaluate.conditions or [] if c not in names]
        if unknown:
            raise ConfigError(f"{where}evaluate.conditions: unknown condition(s) {unknown}; known: {', '.join(sorted(names))}")
        clean = run.metric.rho.clean_condition
        if clean is not None and clean not in names:
            raise ConfigError(f"{where}metric.rho.clean_condition={clean!r} is not a condition; known: {', '.join(sorted(names))}")
    exposures = run.camera.get("overrides") or {}
    if exposures and run.conditions:  # Camera.exposure looks them up by these names
        from pairedgta.conditions import build_condition_grid

        grid = build_condition_grid(run.conditions)
        valid = [*grid.names, *dict.fromkeys(c.time for c in grid)]
        bad = [str(k) for k in exposures if str(k) not in valid]
        if bad:
            raise ConfigError(f"{where}camera.overrides.{bad[0]} is not a condition or time of this run, so no image "
                              f"would use it; use one of {', '.join(valid)}")
    renderer = run.renderer
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
                raise ConfigError(f"{where}{exc}") from None


def check_run_config(cfg: dict[str, Any]) -> RunConfig:
    """Raise one ConfigError for the first bad value of a resolved run config (see the module doc), else return
    the run's typed config. The first step of every run, so it also starts the run's cache of composed model configs."""
    from pairedgta import configs

    configs.reset_cache()
    check_cache_dir(cfg.get("cache_dir"))
    typed = [(where, pcfg, schema.parse(pcfg, where)) for where, pcfg in passes(cfg)]
    names: set[str] = set()
    for where, pcfg, _ in typed:
        names |= set(condition_names(pcfg))
    for where, pcfg, run in typed:
        for key, kind, ok, use, optional in RULES:
            value = _get(pcfg, key)
            if value is None or value == MISSING:
                if optional or key.split(".")[0] not in pcfg:
                    continue
                raise ConfigError(f"{where}{key} is not set; {use}")
            if not ok(schema.number(value, kind, f"{where}{key}", _hint(key))):
                raise ConfigError(f"{where}{key}={value!r} is out of range; {use}")
        _known_model(run.reference_model, f"{where}reference_model")
        check_plot(run, names, where)
        check_transmittance(run, where)
        check_corruptions(run, where)
        check_stage_keys(run, set(condition_names(pcfg)), where)
    for i, name in enumerate(typed[0][2].models or []):
        _known_model(name, f"models[{i}]")
    for i, name in enumerate(typed[0][2].report.population or []):  # the model report's population
        _known_model(name, f"report.population[{i}]")
    return typed[0][2]


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


_TREES: dict[tuple[str, int, int], Any] = {}  # (path, size, mtime) -> its tree


def _load_yaml(path: Path) -> Any:
    """A config file's tree (plain YAML: a tenth of OmegaConf.load's time; only its keys are read, never
    changed). Kept per file version: a process that runs the CLI again (a sweep's jobs in one process, a
    notebook, the tests) parses the hundred-odd files the key check reads once, not on every command line."""
    import yaml

    st = path.stat()
    stamp = (str(path), st.st_size, st.st_mtime_ns)
    if stamp not in _TREES:
        _TREES[stamp] = yaml.load(path.read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader)) or {}
    return _TREES[stamp]


def known_key_paths() -> set[str]:
    """Every dotted key some config file of the package defines: config.yaml and the experiments (global),
    each group option under its group (renderer.noise_std), the groups themselves."""
    from pairedgta.configs import CONFIG_DIR

    known: set[str] = set()
    for path in [CONFIG_DIR / "config.yaml", *sorted((CONFIG_DIR / "experiment").glob("*.yaml"))]:
        known |= _paths(_load_yaml(path))
    # a group is a folder of YAML options (not __pycache__, which Python writes into the package's folders)
    for group in (p for p in CONFIG_DIR.iterdir() if p.is_dir() and not p.name.startswith(("_", "."))
                  and p.name not in ("experiment", "hydra", "zoo")):
        known.add(group.name)
        for option in group.glob("*.yaml"):
            known |= _paths(_load_yaml(option), f"{group.name}.")
    from pairedgta.models import model_keys

    return known | {f"model.{k}" for k in model_keys()}  # a model YAML names only what differs from the defaults


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


def package_nodes(choices: dict[str, str]) -> dict[str, tuple[str, str]]:
    """node -> (group, option) for the group options an experiment places under a name of its own
    (`/dataset@acdc: acdc` makes the node `acdc`): their keys exist only once that experiment is chosen."""
    out: dict[str, tuple[str, str]] = {}
    for k, v in choices.items():
        group, at, package = k.partition("@")
        if at and package and not package.startswith("_"):
            out[package] = (group, v)
    return out


def check_package_key(key: str, choices: dict[str, str]) -> bool:
    """False when `key`'s first part is no package node of `choices`; True when it is one and `key` names a key
    of that node's option file; a ConfigError naming the option's keys otherwise."""
    node, _, rest = key.partition(".")
    placed = package_nodes(choices).get(node)
    if placed is None:
        return False
    group, option = placed
    known = group_option_keys(group, option)
    child = rest.split(".")[0]
    if not rest or known is None or child in known:
        return True
    import difflib

    close = difflib.get_close_matches(child, sorted(known), n=1, cutoff=0.6)
    hint = f"did you mean {node}.{close[0]}?" if close else f"its keys are {', '.join(sorted(known))}"
    raise ConfigError(f"{node}.{child} is not a key of {node} ({group}={option}); {hint}")


def check_group_key(key: str, choices: dict[str, Any] | None) -> None:
    """`key` (e.g. renderer.colour) added to a closed group must be a key of the chosen option's file."""
    from pairedgta.configs import CONFIG_DIR

    group, _, rest = key.partition(".")
    option = (choices or {}).get(group) or default_choices().get(group)
    known = group_option_keys(group, str(option)) if option else None
    if known is not None and group == "model":  # a model YAML names only what differs from its family's defaults
        from pairedgta.models import model_keys

        known |= model_keys()
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
