"""First-order model of an InI-HMD: Eqs. (1)–(10) of the design method.

Symbols (mm): ``p_mla`` lenslet pitch; ``g`` display → MLA gap; ``l`` MLA →
intermediate CDP; ``z_ic`` intermediate CDP → eyepiece (group); ``f_ep``
eyepiece focal length; ``z_xp`` eyepiece → viewing window; ``z_cdp`` viewing
window → virtual CDP (positive: in front of the eye). M × N lenslets.

The printed equations divide by quantities that vanish at three operating
points a design actually uses, so they are evaluated here in equivalent
forms that stay finite:

**Sign correction of Eq. (3).** Traced with ideal elements, the chief ray of
each elemental-image centre crosses the viewing-window centre only if z'_xp in
Eqs. (2) and (7) is the distance from the eyepiece to the image of the viewing
window measured *toward the display*: z'_xp = f_ep z_xp/(f_ep − z_xp). The
printed Eq. (3) has (z_xp − f_ep) in the denominator, which flips the sign and,
for z_xp = 0.8 f_ep, makes Eq. (2) wrong by about 8% (p_EI 0.942 instead of
1.025 mm in the tests). The two agree only at z_xp = f_ep, the design
example's own operating point, where z'_xp is infinite either way. lfsim
uses and reports the corrected z'_xp everywhere.

* z_xp = f_ep (viewing window at the eyepiece's back focal point, the design
  example): z'_xp → ∞. Eq. (2) is evaluated as
  ``p_EI = p_MLA (1 + g (f − z_xp)/((l + z_IC)(f − z_xp) + f z_xp))`` and
  Eq. (7)'s factor z'_xp/(g + l + z_IC + z'_xp) as
  ``f z_xp/((g + l + z_IC)(f − z_xp) + f z_xp)``, both → 1 in the limit.
* CDP at 0 D (z_CDP → ∞): Eqs. (7)–(10) are carried as angles seen from the
  viewing window, Δθ = Δp_EIc/z_CDP and θ_EI = p_EIc/z_CDP; lengths on the
  CDP are reported only when z_CDP is finite.
* g = f_MLA (intermediate CDP at infinity, l → ∞): the model is carried in
  d = l + z_IC (MLA → eyepiece, finite) and β = 1/l (→ 0), e.g.
  z_IC/l = dβ − 1 and l/z_IC = 1/(dβ − 1).

Ray positions follow the ideal-element ray trace (see tests): Eq. (2) makes
the chief ray from each elemental-image centre through its lenslet centre
cross the axis at the viewing-window centre.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

INF = math.inf


class IniInputError(ValueError):
    """Physically meaningless first-order inputs (message names the input)."""


@dataclass
class IniFirstOrder:
    # inputs (echoed)
    p_mla: float
    g: float
    l: float  # noqa: E741 - the paper's symbol
    z_ic: float
    z_xp: float
    f_ep: float
    z_cdp: float
    m: int
    n: int
    # outputs
    p_ei: float  # Eq. (2): elemental-image size = pitch on the display
    z_xp_image: float  # Eq. (3), sign-corrected: f z_xp/(f − z_xp) (inf when z_xp = f_ep)
    d_v: float  # Eq. (5): footprint diameter on the viewing window
    D_v: float  # Eq. (6): viewing-window size
    delta_p_eic: float  # Eq. (7): pitch of virtual EI centres on the CDP (inf at 0 D)
    p_eic: float  # Eq. (8): virtual EI size on the CDP (inf at 0 D)
    delta_theta_eic_deg: float  # Eq. (7) as an angle from the viewing window
    theta_eic_deg: float  # Eq. (8) as an angle
    fov_diag_deg: float  # Eq. (10)
    cdp_diopters: float
    f_mla: float

    #: Unit of each field of :meth:`as_dict` (lengths mm, angles deg; m and n are counts).
    UNITS = {"p_mla": "mm", "g": "mm", "l": "mm", "z_ic": "mm", "z_xp": "mm", "f_ep": "mm", "z_cdp": "mm",
             "m": "", "n": "", "p_ei": "mm", "z_xp_image": "mm", "d_v": "mm", "D_v": "mm", "delta_p_eic": "mm",
             "p_eic": "mm", "delta_theta_eic_deg": "deg", "theta_eic_deg": "deg", "fov_diag_deg": "deg",
             "cdp_diopters": "D", "f_mla": "mm"}

    def as_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in asdict(self).items()}

    # Eq. (1), (4), (9): centres of lenslet, elemental image and virtual EI (m, n 1-based)
    def lenslet_center(self, m: int, n: int) -> tuple[float, float]:
        return (2 * m - self.m - 1) * self.p_mla / 2, (2 * n - self.n - 1) * self.p_mla / 2

    def ei_center(self, m: int, n: int) -> tuple[float, float]:
        return (2 * m - self.m - 1) * self.p_ei / 2, (2 * n - self.n - 1) * self.p_ei / 2

    def virtual_ei_center(self, m: int, n: int) -> tuple[float, float]:
        """Eq. (9) on the virtual CDP (mm; inf components at 0 D)."""
        return ((2 * m - self.m - 1) * self.delta_p_eic / 2, (2 * n - self.n - 1) * self.delta_p_eic / 2)


#: Magnitudes of finite inputs (mm, diopters): outside [TINY, HUGE] the products and
#: reciprocals of Eqs. (2)-(10) leave the float64 range (0 is allowed where it means something).
TINY, HUGE = 1e-12, 1e15


def _positive(name, v, allow_inf=False):
    if not isinstance(v, (int, float)) or isinstance(v, bool) or math.isnan(v) or (
            math.isinf(v) and not allow_inf) or v <= 0:
        raise IniInputError(f"{name} = {v!r}: must be a positive number")
    _magnitude(name, v)


def _magnitude(name, v, zero_ok=False):
    """Finite inputs must lie within [TINY, HUGE] in magnitude (inf and nan are checked by the caller)."""
    if math.isfinite(v) and not (TINY <= abs(v) <= HUGE or (zero_ok and v == 0)):
        raise IniInputError(f"{name} = {v!r}: must be {'0 or ' if zero_ok else ''}within "
                            f"{TINY:g}..{HUGE:g} in magnitude")


def ini_first_order(p_mla: float, g: float, f_ep: float, z_xp: float, m: int, n: int, *,
                    l: float | None = None, f_mla: float | None = None,  # noqa: E741
                    z_ic: float | None = None, cdp_diopters: float | None = None,
                    d_mla_ep: float | None = None) -> IniFirstOrder:
    """Evaluate Eqs. (1)–(10).

    The MLA side is given by ``l`` or ``f_mla`` (then 1/g + 1/l = 1/f_MLA; l = inf
    at g = f_MLA). The eyepiece side by ``z_ic``, or ``d_mla_ep`` (= l + z_IC), or
    ``cdp_diopters`` (then z_IC follows from imaging the intermediate CDP to the
    virtual CDP at z_CDP = 1000/D mm in front of the viewing window).

    References
    ----------
    H. Huang and H. Hua, *Opt. Express* 27(18) (2019): Eqs. (1)–(10), the
    first-order model of an InI-HMD (Eq. 3 sign-corrected, see the module).
    """
    _positive("p_mla", p_mla)
    _positive("g", g)
    _positive("z_xp", z_xp)
    if not isinstance(f_ep, (int, float)) or not math.isfinite(f_ep) or f_ep == 0:
        raise IniInputError(f"f_ep = {f_ep!r}: must be a finite nonzero focal length")
    _magnitude("f_ep", f_ep)
    for name, v in (("m", m), ("n", n)):
        if not isinstance(v, int) or isinstance(v, bool) or v < 1:
            raise IniInputError(f"{name} = {v!r}: must be an integer >= 1")
    # MLA side: beta = 1/l.
    if (l is None) == (f_mla is None):
        raise IniInputError("give exactly one of l and f_mla")
    if f_mla is not None:
        if not math.isfinite(f_mla) or f_mla == 0:
            raise IniInputError(f"f_mla = {f_mla!r}: must be a finite nonzero focal length")
        _magnitude("f_mla", f_mla)
        beta = 1.0 / f_mla - 1.0 / g
    else:
        if not isinstance(l, (int, float)) or math.isnan(l) or l == 0:
            raise IniInputError(f"l = {l!r}: must be a nonzero number or inf")
        _magnitude("l", l)
        beta = 0.0 if math.isinf(l) else 1.0 / l
        power = 1.0 / g + beta  # 0 at l = -g: the "lenslet" is a plate (no power)
        f_mla = INF if power == 0 else 1.0 / power
    l_val = INF if beta == 0 else 1.0 / beta
    # Eyepiece side: d = l + z_IC.
    given = [v is not None for v in (z_ic, cdp_diopters, d_mla_ep)]
    if sum(given) != 1:
        raise IniInputError("give exactly one of z_ic, d_mla_ep and cdp_diopters")
    f = float(f_ep)
    if cdp_diopters is not None:
        if not math.isfinite(cdp_diopters) or cdp_diopters < 0:
            raise IniInputError(f"cdp_diopters = {cdp_diopters!r}: must be a finite number >= 0")
        _magnitude("cdp_diopters", cdp_diopters, zero_ok=True)
        # Virtual CDP at a = z_CDP − z_xp in front of the eyepiece; its object: z_IC = a f/(a + f).
        if cdp_diopters == 0:
            z_ic_val = f
        else:
            a = 1000.0 / cdp_diopters - z_xp
            if a + f == 0:
                raise IniInputError(f"cdp_diopters = {cdp_diopters!r}: puts the intermediate CDP at infinity")
            z_ic_val = a * f / (a + f)
        if math.isinf(l_val):
            raise IniInputError("with g = f_mla the intermediate CDP is at infinity: give d_mla_ep")
        d = l_val + z_ic_val
    elif z_ic is not None:
        if math.isinf(l_val):
            raise IniInputError("with g = f_mla the intermediate CDP is at infinity: give d_mla_ep")
        _magnitude("z_ic", z_ic, zero_ok=True)
        z_ic_val = float(z_ic)
        d = l_val + z_ic_val
    else:
        _magnitude("d_mla_ep", d_mla_ep, zero_ok=True)
        d = float(d_mla_ep)
        z_ic_val = d - l_val if math.isfinite(l_val) else -INF
    if not math.isfinite(d):
        raise IniInputError(f"MLA to eyepiece distance = {d!r}: must be finite")
    zic_over_l = d * beta - 1.0  # z_IC / l

    # Eq. (3), sign-corrected (see the module docstring), and Eq. (2).
    z_img = INF if z_xp == f else f * z_xp / (f - z_xp)
    den2 = d * (f - z_xp) + f * z_xp  # (l + z_IC)(f − z_xp) + f z_xp
    if den2 == 0:
        raise IniInputError("the viewing window's image lies on the MLA: Eq. (2) is singular")
    p_ei = p_mla * (1.0 + g * (f - z_xp) / den2)
    # Virtual CDP: the eyepiece images the intermediate CDP (z_IC in front of it).
    if beta == 0:  # intermediate CDP at infinity: imaged on the eyepiece's back focal plane
        z_cdp = z_xp - f
    else:
        z_cdp = INF if z_ic_val == f else z_xp + z_ic_val * f / (f - z_ic_val)
    # Eq. (5) and (6).
    d_v = p_mla * abs(zic_over_l * (1.0 - z_xp / f) + z_xp * beta)
    D_v = p_ei / g * abs(d * (1.0 - z_xp / f) + z_xp)  # = p_EI (d/g)|1 − z_xp/f + z_xp/d|, finite at d = 0
    # Eq. (7) as an angle: Δθ = Δp_EI · f/((g + d)(f − z_xp) + f z_xp).
    den7 = (g + d) * (f - z_xp) + f * z_xp
    dtheta = p_ei * f / den7 if den7 != 0 else INF
    # Eq. (8): p_EIc = p_EI (l/(g z_IC)) (z_CDP − z_xp), as an angle θ_EI = p_EIc/z_CDP. With
    # z_CDP − z_xp = z_IC f/(f − z_IC) the factor (l/z_IC)(z_CDP − z_xp) is l f/(f − z_IC),
    # finite where the intermediate CDP lies on the eyepiece (z_IC = 0).
    l_over_zic = 1.0 / zic_over_l if zic_over_l != 0 else INF
    finite = math.isfinite(z_cdp)
    if beta != 0 and z_ic_val != f:
        lf = l_val * f / (f - z_ic_val)
    else:  # l = inf (l/z_IC = −1) or the virtual CDP at infinity
        lf = l_over_zic * (z_cdp - z_xp) if finite else INF
    if z_cdp == 0:  # the CDP lies on the viewing window: no finite angular size
        theta_ei = INF
    elif finite:
        theta_ei = abs(p_ei * lf / (g * z_cdp))
    else:
        theta_ei = abs(p_ei * l_over_zic / g)
    fov = 2.0 * math.degrees(math.atan(math.hypot(m, n) / 2.0 * abs(dtheta)))
    return IniFirstOrder(
        p_mla=p_mla, g=g, l=l_val, z_ic=z_ic_val, z_xp=z_xp, f_ep=f, z_cdp=z_cdp, m=m, n=n,
        p_ei=p_ei, z_xp_image=z_img, d_v=d_v, D_v=D_v,
        delta_p_eic=dtheta * z_cdp if finite and math.isfinite(dtheta) else INF,
        p_eic=abs(p_ei * lf / g) if finite else INF,
        delta_theta_eic_deg=math.degrees(math.atan(dtheta)) if math.isfinite(dtheta) else INF,
        theta_eic_deg=math.degrees(math.atan(theta_ei)) if math.isfinite(theta_ei) else INF,
        fov_diag_deg=fov, cdp_diopters=(1000.0 / z_cdp if finite and z_cdp != 0 else 0.0),
        f_mla=f_mla,
    )
