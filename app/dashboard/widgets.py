"""What the page's panels share about viser's widgets."""

from __future__ import annotations

from typing import Any


def assign(handle: Any, value: Any) -> None:
    """Set a widget's value from the server (viser types ``value`` read-only on some handles)."""
    handle.value = value
