"""One construction style for every configurable object: renderers, regions, datasets, model families
(figures declare a `FigureSpec` of their own in pairedgta/figures/__init__.py).

A `Registry` maps a choice (`renderer.backend`, `region.type`, `dataset.kind`, `model.family`) to a lazily
imported `"module:attr"` target, so optional dependencies (bpy, pyzmq, transformers) load only when used.
Every target is called as `target(**config, **runtime)` and declares the keys it accepts in its keyword
signature; `check_keys` rejects an unknown key the same way for all of them, naming the config key and
the keys that exist.
"""
from __future__ import annotations

import ast
import contextlib
import functools
import importlib
import importlib.util
import inspect
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


class Registry:
    """name -> "module:attr" (+ metadata such as the stage a figure reads)."""

    def __init__(self, kind: str, key: str) -> None:
        self.kind = kind  # what is built, for messages: "renderer", "figure"
        self.key = key  # the config key that names the choice: "renderer.backend"
        self._targets: dict[str, str] = {}
        self._meta: dict[str, dict[str, Any]] = {}

    def register(self, name: str, target: str, **meta: Any) -> None:
        if ":" not in target:
            raise ValueError(f"{self.kind} {name}: target must be 'module:attr', got {target!r}")
        self._targets[name] = target
        self._meta[name] = meta

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
        self._check_name(name)
        module_name, attr = self._targets[name].split(":")
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

    def _function_node(self, name: str) -> tuple[str, Any] | None:
        self._check_name(name)
        module_name, attr = self._targets[name].split(":")
        tree = _module_tree(module_name)
        node = next((n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == attr), None) if tree else None
        return (module_name, node) if node is not None else None

    def declared_keys(self, name: str) -> set[str] | None:
        """The keyword names a plain-function target accepts, read from its module's source, so checking
        a config does not import the module (a model family imports torch and transformers). None when
        the source does not say (then `resolve` and `accepted_keys`)."""
        found = self._function_node(name)
        if found is None or found[1].args.kwarg is not None:
            return None
        args = found[1].args
        return {a.arg for a in [*args.posonlyargs, *args.args, *args.kwonlyargs]} - {"self"}

    def declared_defaults(self, name: str) -> dict[str, Any]:
        """The literal keyword-only defaults of a plain-function target, read from its source like
        `declared_keys` (a module-level constant, also one imported from another module, is literal)."""
        found = self._function_node(name)
        if found is None:
            return {}
        module_name, node = found
        out = {}
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
