"""One construction style for every configurable object: renderers, regions, datasets, model families
(figures declare a `FigureSpec` of their own in pairedgta/figures/__init__.py).

A `Registry` maps a choice (`renderer.backend`, `region.type`, `dataset.kind`, `model.family`) to a lazily
imported `"module:attr"` target, so optional dependencies (bpy, pyzmq, transformers) load only when used.
Every target is called as `target(**config, **runtime)` and declares the keys it accepts in its keyword
signature; `check_keys` rejects an unknown key the same way for all of them, naming the config key and
the keys that exist. A target registered `via` a shared builder (timm's `build_model_with_cfg`: the in-project
model families) declares only its own keyword-only arguments; the builder adds the ones every such target shares.
"""
from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import importlib.util
import inspect
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

from pairedgta.errors import ConfigError


def accepted_keys(target: Callable[..., Any]) -> set[str] | None:
    """Keyword names `target` accepts, or None if it takes **kwargs (then it must check them itself)."""
    params = inspect.signature(target).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return {p.name for p in params if p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
            and p.name != "self"}


def check_keys(target: Callable[..., Any] | set[str] | None, keys: Iterable[str], where: str,
               runtime: Iterable[str] = ()) -> None:
    """One-line error for keys `target` does not read (a callable, or the set of its keyword names).
    `where` is the config node, e.g. `renderer`."""
    known = set(target) if isinstance(target, (set, frozenset)) else accepted_keys(target) if target else None
    if known is None:
        return
    known -= set(runtime)
    unknown = sorted(set(keys) - known)
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)}; known keys: {', '.join(sorted(known))}"
        )


def required_keys(target: Callable[..., Any], runtime: Iterable[str] = ()) -> set[str]:
    params = inspect.signature(target).parameters.values()
    return {p.name for p in params if p.default is inspect.Parameter.empty and p.name != "self"
            and p.kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)} - set(runtime)


# A target module's defaults for its shared builder's arguments (timm's pretrained_cfg), a literal dict, e.g. the
# input a family's released weights expect: `PRETRAINED = {"pad_multiple": 32}` in pairedgta/models/ddrnet.py.
VIA_DEFAULTS = "PRETRAINED"


class Registry:
    """name -> "module:attr" (+ metadata such as the stage a figure reads).

    `register(name, target, via="module:attr")`: `target` is built by the shared builder `via`, called as
    `via(target, **config, **runtime)`. The keys of a config are then the keyword-only arguments of both (the
    target's positional ones are the builder's to give, e.g. the model name); a key's one default is the
    target's own, else the target module's `PRETRAINED` entry, else the builder's. `resolve` returns that
    combination as one function with that signature, and `declared_keys` / `declared_defaults` read the same
    from the sources."""

    def __init__(self, kind: str, key: str) -> None:
        self.kind = kind  # what is built, for messages: "renderer", "figure"
        self.key = key  # the config key that names the choice: "renderer.backend"
        self._targets: dict[str, str] = {}
        self._meta: dict[str, dict[str, Any]] = {}

    def register(self, name: str, target: str, *, via: str | None = None, **meta: Any) -> None:
        for what in [target] + ([via] if via else []):
            if ":" not in what:
                raise ValueError(f"{self.kind} {name}: target must be 'module:attr', got {what!r}")
        self._targets[name] = target
        self._meta[name] = dict(meta, via=via) if via else meta

    def names(self) -> list[str]:
        return sorted(self._targets)

    def __contains__(self, name: object) -> bool:
        return name in self._targets

    def meta(self, name: str) -> dict[str, Any]:
        self._check_name(name)
        return self._meta[name]

    def _check_name(self, name: Any) -> None:
        if name not in self._targets:
            raise ConfigError(f"{self.key}={name!r} is unknown; choose one of: {', '.join(self.names())}")

    def resolve(self, name: str) -> Callable[..., Any]:
        """The callable `build` calls: the target, or for a target registered `via` a builder, the two as one."""
        self._check_name(name)
        target = self._import(name, self._targets[name])
        via = self._meta[name].get("via")
        return target if via is None else _through(self._import(name, via), target)

    def _import(self, name: str, where: str) -> Callable[..., Any]:
        module_name, attr = where.split(":")
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.split(".")[0] == "pairedgta":
                raise
            raise ConfigError(
                f"{self.key}={name} needs the Python package '{exc.name}', which is not installed; "
                f"install the project as the README says (pip install -e .)"
            ) from None
        return getattr(module, attr)

    def _function_nodes(self, name: str) -> list[tuple[str, ast.FunctionDef]] | None:
        """(module, function node) of the target, and of its builder first when it has one; None when the
        source does not say."""
        self._check_name(name)
        via = self._meta[name].get("via")
        out = []
        for where in ([via] if via else []) + [self._targets[name]]:
            module_name, attr = where.split(":")
            tree = _module_tree(module_name)
            node = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == attr), None) if tree else None
            if node is None:
                return None
            out.append((module_name, node))
        return out

    def declared_keys(self, name: str) -> set[str] | None:
        """The keyword names a plain-function target accepts, read from its module's source, so checking
        a config does not import the module (a model family imports torch and transformers). None when
        the source does not say (then `resolve` and `accepted_keys`)."""
        found = self._function_nodes(name)
        if found is None:
            return None
        if len(found) == 1:
            args = found[0][1].args
            if args.kwarg is not None:
                return None
            return {a.arg for a in [*args.posonlyargs, *args.args, *args.kwonlyargs]} - {"self"}
        if found[1][1].args.kwarg is not None:  # built via a builder: the target's own **kwargs would say nothing
            return None
        return {a.arg for _, node in found for a in node.args.kwonlyargs}

    def declared_defaults(self, name: str) -> dict[str, Any]:
        """The literal keyword-only defaults of a plain-function target, read from its source like
        `declared_keys` (a module-level constant, also one imported from another module, is literal); for a
        target built `via` a builder, the builder's, its module's PRETRAINED entries, then its own."""
        found = self._function_nodes(name)
        if found is None:
            return {}
        out: dict[str, Any] = {}
        for i, (module_name, node) in enumerate(found):
            if i == 1:  # the target's module, after its builder's defaults: its own for the builder's arguments
                with contextlib.suppress(ValueError):
                    out.update(_literal(ast.Name(VIA_DEFAULTS), module_name))
            for arg, default in zip(node.args.kwonlyargs, node.args.kw_defaults):
                if default is not None:
                    with contextlib.suppress(ValueError):
                        out[arg.arg] = _literal(default, module_name)
        return out

    def build(self, name: str, config: Mapping[str, Any], where: str | None = None, **runtime: Any) -> Any:
        """`target(**config, **runtime)` after checking that `config` holds only keys the target reads."""
        target = self.resolve(name)
        where = where or self.key.split(".")[0]
        check_keys(target, config, where, runtime=runtime)
        missing = sorted(required_keys(target, runtime) - set(config))
        if missing:
            raise ConfigError(f"{where}: missing key(s) {', '.join(missing)} for {self.key}={name}")
        return target(**dict(config), **runtime)


def _through(builder: Callable[..., Any], target: Callable[..., Any]) -> Callable[..., Any]:
    """`builder(target, **config)` as one function whose keyword-only signature is the builder's arguments,
    with the target module's PRETRAINED defaults, followed by the target's keyword-only arguments."""
    def keyword_only(fn: Callable[..., Any]) -> list[inspect.Parameter]:
        return [p for p in inspect.signature(fn).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY]

    own, arch = keyword_only(builder), keyword_only(target)
    shared = {p.name for p in own}
    preset = dict(getattr(sys.modules[target.__module__], VIA_DEFAULTS, {}))
    where = f"{target.__module__}.{target.__name__} (built by {builder.__module__}.{builder.__name__})"
    if shared & {p.name for p in arch}:  # programming errors in the target's module, never a config's
        raise ValueError(f"{where}: {', '.join(sorted(shared & {p.name for p in arch}))} is the builder's argument")
    if set(preset) - shared:
        raise ValueError(f"{where}: {VIA_DEFAULTS} sets {', '.join(sorted(set(preset) - shared))}, "
                         "which the builder does not take")
    signature = inspect.Signature([p.replace(default=preset[p.name]) if p.name in preset else p for p in own] + arch)

    def build(**config: Any) -> Any:
        bound = signature.bind(**config)
        bound.apply_defaults()
        return builder(target, **bound.arguments)

    build.__signature__ = signature  # type: ignore[attr-defined]
    build.__name__ = build.__qualname__ = target.__name__
    build.__module__, build.__doc__ = target.__module__, target.__doc__
    return build


@functools.lru_cache(maxsize=None)
def _module_tree(module_name: str) -> ast.Module | None:
    try:
        spec = importlib.util.find_spec(module_name)
        source = Path(spec.origin).read_text(encoding="utf-8") if spec and spec.origin else None
    except (ImportError, OSError, ValueError):
        return None
    return ast.parse(source) if source else None


def _literal(node: ast.expr, module_name: str, depth: int = 0) -> Any:
    """`ast.literal_eval`, where a bare name is followed to its module-level assignment or import."""
    if not isinstance(node, ast.Name):
        return ast.literal_eval(node)
    tree = _module_tree(module_name)
    if tree is None or depth > 4:
        raise ValueError(node.id)
    for stmt in tree.body:
        if isinstance(stmt, ast.Assign) and any(isinstance(t, ast.Name) and t.id == node.id for t in stmt.targets):
            return _literal(stmt.value, module_name, depth + 1)
        if isinstance(stmt, ast.ImportFrom) and stmt.module and not stmt.level:
            alias = next((a for a in stmt.names if (a.asname or a.name) == node.id), None)
            if alias is not None:
                return _literal(ast.Name(alias.name), stmt.module, depth + 1)
    raise ValueError(node.id)


__all__ = ["Registry", "accepted_keys", "check_keys", "required_keys"]
