"""Test helpers: small designs and a programmatic path reversal."""

from __future__ import annotations

import numpy as np

from lfsim.optics.reverse import euler_xyz, reversed_system  # noqa: F401  (re-exported for tests)


def trace_np(tracer, o, d, values=None, wavelength_nm=None):
    """Trace numpy rays with a SequentialTracer; numpy results (p, d, status, opl)."""
    import drjit as dr

    P = tracer.params(wavelength_nm, values=values)
    with dr.suspend_grad():
        out = tracer.trace(P, tracer.rays(o, d))
    p = np.stack([np.asarray(out.p[i]) for i in range(3)], axis=1)
    dd = np.stack([np.asarray(out.d[i]) for i in range(3)], axis=1)
    return p, dd, np.asarray(out.status), np.asarray(out.opl)
