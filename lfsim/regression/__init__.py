"""Image-quality regression tests: a design re-rendered and re-analysed against a stored baseline.

``lfsim regress`` and the pytest fixture ``lfsim_regression`` use
:func:`update` (create a baseline) and :func:`check` (compare a candidate).
The noise model is in :mod:`.noise`, the baseline folder in :mod:`.baseline`,
the checks and their table in :mod:`.checks`, JUnit XML in :mod:`.junit`.
"""

from .baseline import BaselineError
from .checks import Check
from .run import DEFAULT_OPTIONS, RegressionInputError, RegressionResult, check, update

__all__ = ["BaselineError", "Check", "DEFAULT_OPTIONS", "RegressionInputError", "RegressionResult", "check",
           "update"]
