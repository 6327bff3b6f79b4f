"""The layering the redesign set up, checked on the source: figures import no stage, each stage's file
names appear only in the module of the stage that writes them, construction goes through registries."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "pairedgta"


def imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text())
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
    return out


def string_literals(path: Path) -> set[str]:
    return {n.value for n in ast.walk(ast.parse(path.read_text())) if isinstance(n, ast.Constant) and isinstance(n.value, str)}


@pytest.mark.parametrize("path", sorted((PKG / "figures").glob("*.py")), ids=lambda p: p.name)
def test_figures_import_no_stage(path):
    assert not {m for m in imports(path) if m.startswith("pairedgta.stages")}, path


@pytest.mark.parametrize("path", sorted((PKG / "evaluation").glob("*.py")), ids=lambda p: p.name)
def test_evaluation_imports_no_stage(path):
    """pairedgta/evaluation holds the evaluate stage's jobs below the stage: it must not reach back up."""
    assert not {m for m in imports(path) if m.startswith("pairedgta.stages")}, path


@pytest.mark.parametrize("path", sorted((PKG / "detection").rglob("*.py")), ids=lambda p: p.name)
def test_detection_imports_no_stage(path):
    """pairedgta/detection holds the detection task's work below the stages, as evaluation/ holds segmentation's."""
    assert not {m for m in imports(path) if m.startswith("pairedgta.stages")}, path


def test_every_task_work_sits_below_the_stages():
    """Each task's work for a stage (pairedgta/tasks.py `Task.work`) imports no stage: the stages call it."""
    import importlib

    from pairedgta import tasks

    for task in tasks.TASKS.values():
        for stage, target in task.work.items():
            module = importlib.import_module(target.split(":")[0])
            assert not {m for m in imports(Path(module.__file__)) if m.startswith("pairedgta.stages")}, (task.name, stage)


def test_no_stage_module_per_task():
    """One module per stage, whatever the task: no stages/<task>_*.py."""
    from pairedgta import stage_registry, tasks

    modules = {p.stem for p in (PKG / "stages").glob("*.py")}
    assert not {m for m in modules for t in tasks.NAMES if m.startswith(f"{t}_")}, modules
    assert {s.module.rsplit(".", 1)[-1] for s in stage_registry.STAGES} <= modules


def test_only_the_task_declarations_name_a_task():
    """No code outside pairedgta/tasks.py names a task (the string "detection", "segmentation") or branches on one;
    the other modules ask the run's task (`tasks.get(run.task)`) for its work, figures, zoo and words."""
    from pairedgta import tasks

    offenders = [path.relative_to(PKG).as_posix() for path in sorted(PKG.rglob("*.py"))
                 if path.name != "tasks.py" and string_literals(path) & set(tasks.NAMES)]
    assert not offenders, offenders


# output files and the only module that may name them
OWNED = {
    "xi.csv": "evaluation/tables.py", "rho_valid.csv": "evaluation/tables.py", "frame_counts.csv": "evaluation/tables.py",
    "pixel_agreement.csv": "evaluation/tables.py", "gt_iou.csv": "evaluation/tables.py",
    "histogram.csv": "evaluation/pseudolabel.py", "quality.csv": "evaluation/pseudolabel.py",
    "timings.csv": "stages/generate.py", "validation.csv": "stages/generate.py",
}


def test_stage_files_are_named_only_by_their_stage():
    offenders = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG).as_posix()
        for name in string_literals(path) & set(OWNED):
            if OWNED[name] != rel:
                offenders.append(f"{rel} names {name} (owned by {OWNED[name]})")
    assert not offenders, offenders


def test_app_only_orchestrates():
    """The app runs the stages of pairedgta/stage_registry.py through each module's `step`: it imports no stage
    module but the planner, names no stage (adding a stage is one module and one registry line), no stage's
    files, and reads no cache."""
    from pairedgta import stage_registry

    stage_modules = {s.module for s in stage_registry.STAGES}
    assert not {m for m in imports(PKG / "app.py") if m.startswith("pairedgta.stages")} - {"pairedgta.stages"}
    assert not {m for m in imports(PKG / "app.py")} & stage_modules
    tree = ast.parse((PKG / "app.py").read_text())
    imported = {a.name for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "pairedgta.stages"
                for a in n.names}
    assert imported == {"planning"}, imported
    assert not string_literals(PKG / "app.py") & set(OWNED)
    summary_keys = {k.value for n in ast.walk(tree) if isinstance(n, ast.Dict) for k in n.keys
                    if isinstance(k, ast.Constant)}  # the returned summary's own keys ("evaluate": {model: path})
    assert not (string_literals(PKG / "app.py") - summary_keys) & set(stage_registry.names())
    assert "glob" not in (PKG / "app.py").read_text()


def test_the_planner_names_no_stage():
    """Which stages run and where a pass keeps their results come from the registry: pairedgta/stages/planning.py
    holds no stage name (it held 15 before the registry)."""
    from pairedgta import stage_registry

    named = {s for s in string_literals(PKG / "stages" / "planning.py") if s in stage_registry.names()}
    assert not named, named


def test_no_hand_made_dispatchers_left():
    """Objects are built through pairedgta.registry: no module keeps its own name -> class table."""
    legacy = ("BACKENDS", "REGION_TYPES", "NEEDS")
    for path in sorted(PKG.rglob("*.py")):
        tree = ast.parse(path.read_text())
        names = {t.id for n in ast.walk(tree) if isinstance(n, (ast.Assign, ast.AnnAssign))
                 for t in (n.targets if isinstance(n, ast.Assign) else [n.target]) if isinstance(t, ast.Name)}
        assert not names & set(legacy), f"{path}: {names & set(legacy)}"


def _part(module: str) -> str:
    """The part of the package a module belongs to: pairedgta.stages.planning -> pairedgta.stages."""
    return ".".join(module.split(".")[:2])


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of `graph` (node -> what it imports), each as the path that closes it: a -> b -> a."""
    state: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 1:
                cycles.append(stack[stack.index(dep):] + [dep])
            elif dep not in state:
                visit(dep)
        stack.pop()
        state[node] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name)
    return cycles


def test_the_package_parts_import_each_other_one_way():
    """Parts of the package depend one way: a part imported back by what it imports (config_checks imported
    stages while stages/planning imported config_checks) works only by the order of first import or by a
    lazy import that hides the knot. Every import counts, lazy ones inside functions too."""
    graph: dict[str, set[str]] = {}
    for path in PKG.rglob("*.py"):
        src = _part(".".join(path.relative_to(PKG.parent).with_suffix("").parts))
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            for name in names:
                if name.startswith("pairedgta.") and _part(name) != src:
                    graph.setdefault(src, set()).add(_part(name))
    cycles = _cycles(graph)
    assert not cycles, [" -> ".join(c) for c in cycles]


def module_imports(root: Path = PKG.parent) -> dict[str, set[str]]:
    """Module -> the modules it imports, over pairedgta/ and the experiments/ scripts (which import each other by
    bare name, their folder on sys.path), every import counted: top-level, inside functions, relative.
    `from pkg import name` points at the submodule pkg.name where there is one, else at pkg itself."""
    files: dict[str, Path] = {}
    for path in (root / "pairedgta").rglob("*.py"):
        parts = path.relative_to(root).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    for path in (root / "experiments").glob("*.py"):
        files[path.stem] = path

    def known(name: str) -> str | None:
        name = name.removeprefix("experiments.")
        while name and name not in files:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {}
    for module, path in files.items():
        package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package[:len(package) - node.level + 1] + ([base] if base else []))
                names = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
            else:
                continue
            graph.setdefault(module, set()).update(t for n in names if (t := known(n)) and t != module)
    return graph


def test_no_module_imports_back_what_imports_it():
    """No module of the package or experiments/ sits in an import circle (a imports b, b imports a, directly or
    through others), lazy imports inside functions included: a function-level import that closes a circle hides
    the knot and works only because it runs after both modules are loaded (evaluation.entry and .registry over
    OWN_FILES, figures.model_report and its page, bench_evaluate and bench_models each had one)."""
    graph = module_imports()
    # both trees are read, imports inside functions too (from a package import its submodule; a script by name)
    assert "pairedgta.evaluation.registry" in graph["pairedgta.evaluation.entry"]
    assert "bench_evaluate" in graph["bench_models"]
    cycles = _cycles(graph)
    assert not cycles, [" -> ".join(c) for c in cycles]


def test_declared_keys_read_from_source_match_the_signatures():
    """Config checks read a target's keyword names from its source (no import of torch or transformers
    for a check); they must be exactly what the imported signature says."""
    from pairedgta.datasets import DATASETS
    from pairedgta.models import FAMILIES
    from pairedgta.registry import accepted_keys

    for registry in (FAMILIES, DATASETS):
        for name in registry.names():
            declared = registry.declared_keys(name)
            if declared is not None:
                assert declared == accepted_keys(registry.resolve(name)), (registry.kind, name)


def test_no_module_over_500_lines():
    """A module past 500 lines has been doing more than one job each time it got there (the test server in
    pairedgta/testing/ mirrors a whole protocol and is exempt)."""
    long = {p.relative_to(PKG).as_posix(): n for p in PKG.rglob("*.py")
            if "testing" not in p.relative_to(PKG).parts and (n := len(p.read_text().splitlines())) > 500}
    assert not long, long


@pytest.mark.slow
def test_the_config_is_parsed_once_per_pass(tmp_path, monkeypatch):
    """The typed config (pairedgta/schema.py) is built once by the run's checks and handed down: the planner,
    the pass's context and its result reuse it (a variant's pass, a config of its own, is parsed once more)."""
    from pairedgta import schema
    from pairedgta.app import run
    from pairedgta.testing.cli import compose_cfg, fast_overrides

    calls = []
    real = schema.parse
    monkeypatch.setattr(schema, "parse", lambda cfg, *a, **k: (calls.append(1), real(cfg, *a, **k))[1])
    run(compose_cfg(fast_overrides(tmp_path) + ["tracking.enabled=false", "plot.figures=[xi_models]"]))
    assert len(calls) == 1


def test_the_model_registry_names_only_its_own_part():
    """A family's builder, loader and check are named by string (no import until built): a name outside
    pairedgta.models would be an import the graph above does not see (detection's models sat in pairedgta/detection,
    which imports pairedgta.models: a hidden loop). Every registered target lies in pairedgta.models."""
    from pairedgta.models import FAMILIES

    outside = []
    for name in FAMILIES.names():
        meta = FAMILIES.meta(name)
        for target in (FAMILIES._targets[name], meta.get("via"),
                       meta.get("check")):
            if isinstance(target, str) and not target.startswith("pairedgta.models."):
                outside.append(f"{name}: {target}")
    assert not outside, outside
    source = (PKG / "models" / "__init__.py").read_text()
    assert "pairedgta.detection" not in source
