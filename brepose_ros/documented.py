"""Dataclass fields that carry their documentation (read by ``params.field_docs`` and the node)."""
from __future__ import annotations

from dataclasses import field
from typing import Any


def doc(text: str, default: Any) -> Any:
    """A dataclass field with its default and its documentation in ``metadata["doc"]``."""
    return field(default=default, metadata={"doc": text})
