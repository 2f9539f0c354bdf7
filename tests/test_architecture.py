"""The layout's rules, checked on the source: the engine is pure, and imports run one way
(engine <- drivers <- service <- api <- cli/benchmarks), at subpackage granularity."""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("autotuner", "drivers", "api")

# Lower number = lower layer. A module may import from its own layer and from lower ones only.
LAYERS = {"engine": 0, "drivers": 1, "service": 2, "api": 3, "cli": 4, "benchmarks": 4}

# Modules the pure engine must never load, directly or through a dependency.
NOT_IN_ENGINE = ("fastapi", "starlette", "sqlalchemy", "pymodbus", "serial", "can", "cantools", "uvicorn",
                 "pydantic", "yaml", "typer", "rich")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def _layer(module: str) -> str | None:
    """The layer of a module of this project; None for third-party modules and the bare ``autotuner``
    package (its ``__version__`` is for everyone)."""
    parts = module.split(".")
    if parts[0] == "drivers":
        return "drivers"
    if parts[0] == "api":
        return "api"
    if parts[0] == "autotuner" and len(parts) > 1:
        if parts[1] not in LAYERS:
            raise AssertionError(f"{module}: autotuner.{parts[1]} is in no layer (add it to LAYERS or move it)")
        return parts[1]
    return None


def _imports(path: Path, source: str | None = None, module: str | None = None) -> list[tuple[int, str]]:
    """Every module that ``path`` (or ``source`` as module ``module``) imports, at the top or inside
    functions, relative imports resolved."""
    module = module or _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    tree = ast.parse(path.read_text() if source is None else source, str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
            found.append((node.lineno, base))
    return found


def test_every_module_is_in_a_layer() -> None:
    modules = [_module_name(p) for p in _sources()]
    assert "autotuner.engine.experiment.relay" in modules and "api.app" in modules  # the walk sees the tree
    for module in modules:
        if module != "autotuner":
            assert _layer(module) is not None, module


def test_imports_run_one_way() -> None:
    upward = []
    for path in _sources():
        own = _layer(_module_name(path))
        if own is None:  # autotuner/__init__.py: the version only
            assert [m for _, m in _imports(path) if _layer(m) is not None] == [], path
            continue
        for line, imported in _imports(path):
            theirs = _layer(imported)
            if theirs is not None and LAYERS[theirs] > LAYERS[own]:
                upward.append(f"{path.relative_to(ROOT)}:{line}: {own} imports {imported} ({theirs})")
    assert upward == []


def test_the_walk_resolves_relative_and_nested_imports() -> None:
    """An engine module importing the service, relatively and inside a function, is seen (so a pass means
    something)."""
    source = "from .plant import process\n\ndef f():\n    from ..service import daemon\n    import api.app\n"
    path = ROOT / "autotuner" / "engine" / "probe.py"
    found = [m for _, m in _imports(path, source, "autotuner.engine.probe")]
    assert found == ["autotuner.engine.plant", "autotuner.service", "api.app"]
    assert [_layer(m) for m in found] == ["engine", "service", "api"]


def _engine_modules() -> list[str]:
    return [_module_name(p) for p in sorted((ROOT / "autotuner" / "engine").rglob("*.py"))]


def test_the_engine_loads_no_service_library() -> None:
    modules = _engine_modules()
    assert len(modules) > 20
    code = (
        "import importlib, json, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({list(NOT_IN_ENGINE)!r}))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) == []


def test_the_engine_check_sees_a_service_library() -> None:
    """The same sys.modules check reports pydantic for the API's models (it is sensitive)."""
    code = "import api.models, sys, json; print(json.dumps('pydantic' in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout) is True
