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


#: The small InI design of :func:`small_ini` (mm): display gap, ideal lenslets, an ideal
#: tunable lens and eyepiece, then two real singlets W (biconvex) and M (meniscus) before the
#: viewing window.
SMALL = dict(g=4.5, f_mla=3.5, l_tl=46.75, f_ep=45.0, gap_ep_w=10.0, r_w=100.0, t_w=3.0, gap_w_m=4.0,
             r_m1=60.0, t_m=2.0, r_m2=80.0, t_vw=12.0)


def small_ini(m2_radius: float | None = SMALL["r_m2"], glass: str = '"N-BK7"', wavelengths=(587.5618,)) -> str:
    """TOML of a 5 × 3 InI design of :data:`SMALL` (``m2_radius`` None: M's back face flat;
    ``glass``: the singlets' material value as written in TOML)."""
    s = SMALL
    m2 = f"radius = {m2_radius}" if m2_radius is not None else "radius = inf"
    return f'''
name = "small InI test design"
[system]
wavelengths_nm = {list(wavelengths)}
[object]
distance = {s["g"]}
[arrays.mla]
m = 5
n = 3
pitch = [1.0, 1.0]
[[surfaces]]
name = "MLA"
type = "paraxial"
focal_length = {s["f_mla"]}
array = "mla"
aperture = {{ type = "rectangular", half_width = [0.5, 0.5] }}
thickness = {s["l_tl"]}
[[surfaces]]
name = "TL"
type = "paraxial"
focal_length = inf
thickness = 0.0
semi_diameter = 10.0
[[surfaces]]
name = "EP"
type = "paraxial"
focal_length = {s["f_ep"]}
thickness = {s["gap_ep_w"]}
semi_diameter = 10.0
[[surfaces]]
name = "W1"
radius = {s["r_w"]}
thickness = {s["t_w"]}
material = {glass}
semi_diameter = 12.0
[[surfaces]]
name = "W2"
radius = {-s["r_w"]}
thickness = {s["gap_w_m"]}
semi_diameter = 12.0
[[surfaces]]
name = "M1"
radius = {s["r_m1"]}
thickness = {s["t_m"]}
material = {glass}
semi_diameter = 10.0
[[surfaces]]
name = "M2"
{m2}
thickness = {s["t_vw"]}
semi_diameter = 10.0
[[surfaces]]
name = "VW"
dummy = true
[ini]
mla = "mla"
pixel_pitch = 0.008
pixels_per_ei = [125, 125]
cdp_diopters = [0.0, 1.0, 3.0]
viewing_window = "VW"
[ini.tunable]
surface = "TL"
range_diopters = [-30.0, 30.0]
'''
