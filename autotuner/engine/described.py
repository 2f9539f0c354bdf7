"""Dataclass fields that say what they hold: the one way the engine's result types describe their fields."""

from __future__ import annotations

from dataclasses import MISSING, field
from typing import Any


def described(description: str, default: Any = MISSING, *, example: Any = MISSING) -> Any:
    """A dataclass field with its ``description`` (unit included) and an ``example`` in ``metadata``, the keys
    pydantic reads into a JSON schema; ``default`` as for :func:`dataclasses.field`."""
    metadata: dict[str, Any] = {"description": description}
    if example is not MISSING:
        metadata["examples"] = [example]
    return field(default=default, metadata=metadata)
