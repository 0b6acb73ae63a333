"""The one error type of design-file loading: file, key, value, what is allowed."""

from __future__ import annotations


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

    def __init__(self, file: str, key: str, value, allowed: str):
        self.file, self.key, self.value, self.allowed = str(file), key, value, allowed
        shown = "missing" if value is _MISSING else repr(value)
        if len(shown) > 80:
            shown = shown[:77] + "..."
        text = f"{self.file}: {key} = {shown}: {allowed}" if key else f"{self.file}: {allowed}"
        super().__init__(" ".join(text.split()))


class _Missing:
    def __repr__(self) -> str:
        return "missing"


_MISSING = _Missing()
MISSING = _MISSING
