"""lfsim: physically based light-field simulator for integral-imaging HMDs."""

from .design import Design, DesignError, TraceResult, load

__version__ = "0.1.0"
__all__ = ["Design", "DesignError", "TraceResult", "load", "__version__"]
