"""Every public function, method and class of the engine documents each of its parameters.

Modelled on python-control's control/tests/docstrings_test.py: for each public callable defined in a module
of ``autotuner.engine`` (its name and its module's without a leading underscore), each parameter must be named
in its docstring the way the project names them — in double backquotes, alone (``name``) or in an expression
(``[ta, tb]``), or as ``name:`` at the start of a line or after a space or a semicolon (``a, b:`` documents both), the convention of RelayConfig and
Tolerances. A class's
parameters are its constructor's (documented in the class's or ``__init__``'s docstring); a dataclass field
may instead carry its description (``described``). ``self``, ``cls`` and ``*args``/``**kwargs`` are exempt.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import re
from collections.abc import Callable, Iterator

import pytest

import autotuner.engine

DESCRIPTION = "description"  # autotuner.engine.described keeps a field's description in its metadata


def _modules() -> Iterator[object]:
    for info in pkgutil.walk_packages(autotuner.engine.__path__, "autotuner.engine."):
        if not any(part.startswith("_") for part in info.name.split(".")):
            yield importlib.import_module(info.name)


def _public(module: object) -> Iterator[tuple[str, Callable]]:
    """(qualified name, callable) of the module's own public functions, classes and their methods."""
    for name, value in vars(module).items():
        if name.startswith("_") or getattr(value, "__module__", None) != module.__name__:
            continue
        if inspect.isfunction(value):
            yield f"{module.__name__}.{name}", value
        elif inspect.isclass(value):
            yield f"{module.__name__}.{name}", value
            for attr, member in vars(value).items():
                if inspect.isfunction(member) and not attr.startswith("_"):
                    yield f"{module.__name__}.{name}.{attr}", member
                elif isinstance(member, (staticmethod, classmethod)) and not attr.startswith("_"):
                    yield f"{module.__name__}.{name}.{attr}", member.__func__


def documented(name: str, doc: str) -> bool:
    """True when ``name`` is named in ``doc`` in double backquotes (alone or in an expression: ``[ta, tb]``) or
    as ``name:`` at a line's start or after a space or a semicolon (``a, name:``)."""
    word = re.compile(rf"\b{re.escape(name)}\b")
    if any(word.search(quoted) for quoted in re.findall(r"``(.+?)``", doc, re.DOTALL)):
        return True
    return re.search(rf"(^|[\s;])(\w+, )*{re.escape(name)}(, \w+)*:", doc, re.MULTILINE) is not None


def missing(target: Callable) -> list[str]:
    """The parameters of ``target`` (a function or a class) its docstrings leave undocumented."""
    if inspect.isclass(target):
        if target.__init__ is object.__init__:
            return []
        described = {f.name for f in dataclasses.fields(target) if DESCRIPTION in f.metadata} \
            if dataclasses.is_dataclass(target) else set()
        doc = (target.__doc__ or "") + "\n" + (inspect.getdoc(target.__init__) or "")
        signature = inspect.signature(target.__init__)
    else:
        described = set()
        doc = inspect.getdoc(target) or ""
        signature = inspect.signature(target)
    names = [p.name for p in signature.parameters.values()
             if p.name not in ("self", "cls") and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    return [n for n in names if n not in described and not documented(n, doc)]


CALLABLES = sorted((name, target) for module in _modules() for name, target in _public(module))


def test_the_engine_has_public_callables_to_check() -> None:
    assert len(CALLABLES) > 100


@pytest.mark.parametrize("name, target", CALLABLES, ids=[name for name, _ in CALLABLES])
def test_every_parameter_is_documented(name: str, target: Callable) -> None:
    assert not missing(target), f"{name} leaves undocumented: {', '.join(missing(target))}"


def test_an_undocumented_parameter_fails() -> None:
    def scale(value: float, factor: float) -> float:
        """``value`` times the factor."""
        return value * factor

    def scaled(value: float, factor: float) -> float:
        """``value`` times ``factor``."""
        return value * factor

    @dataclasses.dataclass
    class Pair:
        """first: one thing."""

        first: float
        second: float

    assert missing(scale) == ["factor"] and missing(scaled) == [] and missing(Pair) == ["second"]
    assert documented("mv_limits", "pv_limits, mv_limits: ranges") and not documented("mv", "mv_limits: ranges")
    assert documented("tb", "over ``[ta, tb]``") and not documented("t", "over ``[ta, tb]``")
