"""The one error type of design-file loading: file, key, value, what is allowed."""

from __future__ import annotations

import re
from contextlib import contextmanager


class DesignError(ValueError):
    """Bad design input. ``str(err)`` is a single line naming file, key and value.

    Attributes
    ----------
    file : str
        The design file (or ``"<dict>"`` for in-memory designs).
    key : str
        Dotted path of the offending key, e.g. ``surfaces[3].radius``.
    value : object
        The value found (``None`` when the key is missing).
    allowed : str
        What would have been accepted.
    """

    def __init__(self, file: str, key: str, value, allowed: str, surface: str | None = None):
        self.file, self.key, self.value, self.allowed = str(file), key, value, allowed
        #: The name of the surface ``key`` points into (``surfaces[i]...``), when it has one.
        self.surface = surface
        shown = "missing" if value is _MISSING else repr(value)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        if surface is not None:
            shown += f" (surface {surface!r})"
        text = f"{self.file}: {key} = {shown}: {allowed}" if key else f"{self.file}: {allowed}"
        super().__init__(" ".join(text.split()))


_SURFACE_KEY = re.compile(r"^surfaces\[(\d+)\]")


@contextmanager
def surface_names(raw: dict):
    """Re-raise a :class:`DesignError` whose key points into ``surfaces[i]`` with that
    surface's name in the message (a file's surfaces are known by name, not by index)."""
    try:
        yield
    except DesignError as e:
        m = _SURFACE_KEY.match(e.key or "")
        rows = raw.get("surfaces") if isinstance(raw, dict) else None
        if e.surface is not None or m is None or not isinstance(rows, list) or int(m.group(1)) >= len(rows):
            raise
        row = rows[int(m.group(1))]
        name = row.get("name") if isinstance(row, dict) else None
        if not isinstance(name, str):
            raise
        raise DesignError(e.file, e.key, e.value, e.allowed, surface=name) from None


class _Missing:
    def __repr__(self) -> str:
        return "missing"


_MISSING = _Missing()
MISSING = _MISSING
