"""Design files: schema, loading and validation (no Dr.Jit, no Mitsuba)."""

from .design import Design, TraceResult, load
from .errors import DesignError

__all__ = ["Design", "DesignError", "TraceResult", "load"]
