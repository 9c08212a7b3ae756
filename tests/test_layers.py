"""The package layers look only down (README "Layers").

Every ``.py`` under ``service/``, ``schemas/``, ``clients/`` and ``sim_publisher/`` is parsed
with :mod:`ast`; every import statement counts, at module level or inside a function, ``import
x`` and ``from x import y`` (relative ones resolved), also under ``if TYPE_CHECKING``. Each
layer's rule says which project packages it may import and which third-party packages it must
not; a failure lists ``file:line: import ... (rule)`` for every offending import.

Two consequences of Python's import system are checked too: importing ``a.b.c`` runs
``a/__init__.py`` and ``a/b/__init__.py``, so a package's ``__init__`` must obey the rule of
every module inside it; and a forbidden third-party package must not be reached indirectly
through the project modules a layer imports.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("service", "schemas", "clients", "sim_publisher")


@dataclass(frozen=True)
class Rule:
    """What the modules under ``prefixes`` may import.

    ``allowed``: project packages they may import (``None``: any, minus ``forbidden``);
    ``forbidden``: project or third-party packages they must not import, directly or (for
    third-party ones) through the project modules they import.
    """

    name: str
    prefixes: tuple[str, ...]
    allowed: tuple[str, ...] | None
    forbidden: tuple[str, ...] = ()


ADAPTERS = ("service.adapters.logs", "service.adapters.maps", "service.adapters.convert")
#: First matching rule wins (most specific first).
RULES: tuple[Rule, ...] = (
    Rule("service.errors", ("service.errors",), allowed=()),
    Rule(
        "schemas.ros2.*",
        ("schemas.ros2",),
        allowed=("schemas", "service.errors"),
        forbidden=("zenoh",),
    ),
    Rule("schemas.*", ("schemas",), allowed=("schemas", "service.errors")),
    Rule(
        "service.core.*",
        ("service.core",),
        allowed=("service.core", "service.errors"),
        forbidden=("zenoh", "msgpack", "schemas"),
    ),
    Rule(
        "service.adapters.logs.*, service.adapters.maps.*, service.adapters.convert",
        ADAPTERS,
        allowed=("service.core", "service.errors", "schemas", *ADAPTERS),
        forbidden=("zenoh",),
    ),
    Rule(
        "service (node, workers, settings, state, __main__)",
        ("service",),
        allowed=None,
        forbidden=("clients", "sim_publisher"),
    ),
    Rule("clients.*", ("clients",), allowed=None, forbidden=("sim_publisher",)),
    Rule("sim_publisher.*", ("sim_publisher",), allowed=None),
)


def _under(module: str, prefix: str) -> bool:
    return module == prefix or module.startswith(prefix + ".")


def _is_project(module: str) -> bool:
    return any(_under(module, p) for p in PACKAGES)


def rule_of(module: str) -> Rule:
    """The rule of a project module (first match of :data:`RULES`)."""
    for rule in RULES:
        if any(_under(module, p) for p in rule.prefixes):
            return rule
    raise AssertionError(f"no layer rule covers module {module!r}")


def module_name(path: Path) -> str:
    """``service/adapters/maps/files.py`` -> ``service.adapters.maps.files``;
    ``service/__init__.py`` -> ``service``."""
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


@cache
def project_modules() -> frozenset[str]:
    return frozenset(module_name(p) for p in source_files())


@cache
def source_files() -> tuple[Path, ...]:
    return tuple(
        sorted(
            p
            for pkg in PACKAGES
            for p in (REPO / pkg).rglob("*.py")
            if "__pycache__" not in p.parts and ".venv" not in p.parts
        )
    )


def imports_of(tree: ast.AST, module: str, is_package: bool) -> list[tuple[int, str, str]]:
    """Every import in ``tree`` as ``(line, imported module, source text)``.

    ``from pkg import name`` counts as importing ``pkg.name`` when that is a project module
    (a submodule), else ``pkg``. Relative imports are resolved against ``module``.
    """
    out: list[tuple[int, str, str]] = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                out.append((node.lineno, alias.name, f"import {alias.name}"))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base_parts = package.split(".")
                base_parts = base_parts[: len(base_parts) - (node.level - 1)]
                base = ".".join(p for p in [*base_parts, node.module or ""] if p)
            else:
                base = node.module or ""
            if base == "__future__":
                continue
            dots = "." * node.level
            for alias in node.names:
                text = f"from {dots}{node.module or ''} import {alias.name}"
                sub = f"{base}.{alias.name}"
                target = sub if sub in project_modules() else base
                out.append((node.lineno, target, text))
    return sorted(out)


@cache
def parsed() -> dict[str, tuple[Path, list[tuple[int, str, str]]]]:
    """module name -> (file, its imports)."""
    out = {}
    for path in source_files():
        name = module_name(path)
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        out[name] = (path, imports_of(tree, name, path.name == "__init__.py"))
    return out


def _violation(rule: Rule, imported: str) -> str | None:
    """Why ``imported`` breaks ``rule`` (``None`` if it does not)."""
    top = imported.split(".")[0]
    for f in rule.forbidden:
        if _under(imported, f) or top == f:
            return f"{rule.name} must never import {f}"
    allowed = rule.allowed
    if allowed is None or not _is_project(imported) or any(_under(imported, a) for a in allowed):
        return None
    return f"{rule.name} may import only {', '.join(allowed) or 'nothing of the project'}"


def _ancestors(module: str) -> list[str]:
    parts = module.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts))]


def _rel(path: Path) -> str:
    return path.relative_to(REPO).as_posix()


def direct_violations(rule: Rule) -> list[str]:
    """Imports of the modules governed by ``rule`` that break it."""
    out = []
    for name, (path, imports) in parsed().items():
        if rule_of(name) is not rule:
            continue
        for line, imported, text in imports:
            why = _violation(rule, imported)
            if why is not None:
                out.append(f"{_rel(path)}:{line}: `{text}` ({why})")
    return out


def package_init_violations() -> list[str]:
    """A package's ``__init__`` runs whenever a module inside it is imported, so it must obey
    the rule of every module inside it."""
    found: dict[tuple[str, int, str, str], list[str]] = {}
    mods = parsed()
    for name in sorted(mods):
        rule = rule_of(name)
        for pkg in _ancestors(name):
            if pkg not in mods:
                continue
            path, imports = mods[pkg]
            for line, imported, text in imports:
                why = _violation(rule, imported)
                if why is not None:
                    found.setdefault((_rel(path), line, text, why), []).append(name)
    out = []
    for (path, line, text, why), names in sorted(found.items()):
        more = f" and {len(names) - 1} more" if len(names) > 1 else ""
        out.append(f"{path}:{line}: `{text}` (importing {names[0]}{more} runs it; {why})")
    return out


def _project_deps(module: str) -> list[str]:
    """Project modules that importing ``module`` executes directly (incl. package inits)."""
    mods = parsed()
    out = []
    for _, imported, _ in mods[module][1]:
        if _is_project(imported):
            out += [m for m in [*_ancestors(imported), imported] if m in mods]
    return out


def transitive_violations() -> list[str]:
    """Third-party packages a layer forbids must not be reached through project imports
    (reported once per layer and offending import, with the shortest chain)."""
    found: dict[tuple[str, int, str, str], str] = {}
    mods = parsed()
    for name in sorted(mods):
        rule = rule_of(name)
        external = {f for f in rule.forbidden if not _is_project(f)}
        if not external:
            continue
        chains = {m: (name, m) for m in [*_ancestors(name), *_project_deps(name)] if m in mods}
        queue = list(chains)
        while queue:  # breadth first: the first chain to a module is a shortest one
            mod = queue.pop(0)
            path, imports = mods[mod]
            for line, imported, text in imports:
                top = imported.split(".")[0]
                if top in external:
                    key = (_rel(path), line, text, f"{rule.name} must never import {top}")
                    found.setdefault(key, " -> ".join(chains[mod]))
            for dep in _project_deps(mod):
                if dep not in chains and dep != name:
                    chains[dep] = (*chains[mod], dep)
                    queue.append(dep)
    return [
        f"{path}:{line}: `{text}` reached via {chain} ({why})"
        for (path, line, text, why), chain in sorted(found.items())
    ]


def _report(violations: list[str]) -> str:
    return "forbidden imports:\n  " + "\n  ".join(violations)


@pytest.mark.parametrize("rule", RULES, ids=[r.name.split(" ")[0].rstrip(",") for r in RULES])
def test_each_layer_imports_only_what_it_may(rule: Rule) -> None:
    governed = [n for n in parsed() if rule_of(n) is rule]
    assert governed, f"no module is governed by {rule.name}"
    violations = direct_violations(rule)
    assert not violations, _report(violations)


def test_package_inits_obey_the_rules_of_their_modules() -> None:
    violations = package_init_violations()
    assert not violations, _report(violations)


def test_forbidden_third_party_packages_are_not_reached_indirectly() -> None:
    violations = transitive_violations()
    assert not violations, _report(violations)


def test_the_import_scan_sees_every_kind_of_import() -> None:
    """The scanner itself: module and function level, ``import`` and ``from``, relative."""
    src = (
        "import zenoh\n"
        "from schemas.messages import Map\n"
        "from service import errors\n"
        "def f():\n"
        "    import msgpack.fallback\n"
        "    from . import world\n"
        "    from ...core.types import MapData\n"
        "class C:\n"
        "    def g(self):\n"
        "        from clients.client import ShapelocClient\n"
    )
    got = imports_of(ast.parse(src), "service.adapters.maps.files", is_package=False)
    assert [(line, mod) for line, mod, _ in got] == [
        (1, "zenoh"),
        (2, "schemas.messages"),
        (3, "service.errors"),  # a submodule named in `from pkg import mod`
        (5, "msgpack.fallback"),
        (6, "service.adapters.maps.world"),
        (7, "service.core.types"),
        (10, "clients.client"),
    ]
    adapters = rule_of("service.adapters.maps.files")
    assert _violation(adapters, "zenoh") == f"{adapters.name} must never import zenoh"
    assert "may import only" in (_violation(adapters, "clients.client") or "")
    assert _violation(adapters, "service.core.types") is None
    assert _violation(adapters, "numpy") is None
    assert rule_of("service.errors").name == "service.errors"
    assert rule_of("service.node.node") is rule_of("service")
    assert rule_of("service.adapters.convert") is adapters
    # the tree is really scanned: every package has modules, and known imports are found
    names = set(parsed())
    assert {"service.errors", "schemas.messages", "clients.client", "sim_publisher.demo"} <= names
    _, client_imports = parsed()["clients.client"]
    assert "service.adapters.maps.files" in {m for _, m, _ in client_imports}


def test_the_wire_owns_the_method_names() -> None:
    """``schemas.messages.METHODS`` (from the ``RobotConfig.method`` Literal) is what the core
    implements: ``service.core.types.METHODS`` is an equal copy (the core cannot import the
    wire)."""
    from schemas.messages import METHODS, RobotConfig
    from service.core.types import METHODS as CORE_METHODS

    assert METHODS == CORE_METHODS == ("shape", "icp", "lines")
    for m in METHODS:
        assert RobotConfig(map_id="m", method=m).method == m
