"""Display primaries as spectra, and the wavelength quadrature of spectral retinal images.

Retinal images are integrated over wavelength in Mitsuba's RGB variant, one
render pass per display channel: every camera ray of channel c's pass carries
one wavelength node of c's primary, picked from the ray's wavelength sample,
and is traced through the design and the eye with that node's glass and
eye-media indices; the pass keeps channel c. A channel's pixel value is

    I_c = ∫ S_c(λ) L_c(x(λ)) dλ / ∫ S_c(λ) dλ

(``S_c`` the channel's emission spectrum, ``x(λ)`` where the ray of
wavelength λ lands on the display): a grey display renders as its grey level,
and every colour fringe of the optics and the eye is in the image.

Why passes: the primaries barely overlap, so a ray that picked one channel's
wavelength at random would feed that channel alone (weight 3 there, 0
elsewhere) and the channel selection alone would add a variance of 2 L² per
sample; a pass per channel keeps every pupil sample of every channel, at
three times the display path's rays. Why not Mitsuba's spectral variants: a
refracting interface sends each wavelength its own way, and Mitsuba's
spectral rays carry four wavelengths along one path (no dispersion of
directions), while the RGB variant with per-ray nodes keeps the exact
reverse trace of the analytic display path, its kernels and its gradients.

Nodes: each channel's spectrum is cut into ``k`` strata of equal emitted power
and sampled at their median wavelengths (the quantiles ``(i + ½)/k`` of its
cumulative spectrum), each of weight ``1/k``; a ray picks one uniformly.
Between the nodes the retinal image varies smoothly with λ (glass and ocular
dispersion), so a few nodes per primary reach the Monte Carlo noise.

Default primaries (:data:`DEFAULT_PRIMARIES`): Gaussian spectra of a colour
OLED microdisplay (a white or RGB OLED behind colour filters, with a
microcavity), peaks 460 / 530 / 620 nm and FWHM 25 / 30 / 35 nm. They are
representative values, chosen so that the primaries' dominant wavelengths lie
near those of the sRGB primaries (464 / 549 / 611 nm: IEC 61966-2-1 primaries
under the CIE 1931 observer), not one panel's measured spectrum: set a real
panel's spectra in the content file's ``[display.primaries]``
(docs/rendering.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..backend import from_numpy

#: Wavelength range the spectra are integrated over (nm).
RANGE_NM = (380.0, 780.0)
CHANNELS = ("R", "G", "B")


@dataclass(frozen=True)
class Primary:
    """One display channel's emission spectrum: a Gaussian (``peak_nm``, ``fwhm_nm``) or
    a table (``wavelengths_nm``, ``values``, linearly interpolated, 0 outside)."""

    peak_nm: float | None = None
    fwhm_nm: float | None = None
    wavelengths_nm: tuple[float, ...] | None = None
    values: tuple[float, ...] | None = None

    def __post_init__(self):
        if self.wavelengths_nm is None:
            for key, v in (("peak_nm", self.peak_nm), ("fwhm_nm", self.fwhm_nm)):
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                    raise ValueError(f"{key} = {v!r}: must be a number > 0 (nm)")
            if not RANGE_NM[0] <= self.peak_nm <= RANGE_NM[1]:
                raise ValueError(f"peak_nm = {self.peak_nm!r}: must lie in {RANGE_NM[0]:g}..{RANGE_NM[1]:g} nm")
            return
        lam = np.asarray(self.wavelengths_nm, dtype=np.float64)
        val = np.asarray(self.values, dtype=np.float64) if self.values is not None else None
        if lam.ndim != 1 or lam.size < 2 or not np.all(np.isfinite(lam)) or np.any(np.diff(lam) <= 0):
            raise ValueError(f"wavelengths_nm = {self.wavelengths_nm!r}: must be >= 2 increasing finite numbers (nm)")
        if val is None or val.shape != lam.shape or not np.all(np.isfinite(val)) or np.any(val < 0) \
                or not np.any(val > 0):
            raise ValueError(f"values = {self.values!r}: must be {lam.size} finite numbers >= 0, not all 0")

    def spectrum(self, lam: np.ndarray) -> np.ndarray:
        """Relative spectral power at ``lam`` (nm)."""
        lam = np.asarray(lam, dtype=np.float64)
        if self.wavelengths_nm is None:
            sigma = self.fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
            return np.exp(-0.5 * ((lam - self.peak_nm) / sigma) ** 2)
        return np.interp(lam, self.wavelengths_nm, self.values, left=0.0, right=0.0)

    def quantiles(self, q: np.ndarray) -> np.ndarray:
        """Wavelengths (nm) at the fractions ``q`` of the emitted power (inverse CDF)."""
        lam = np.linspace(*RANGE_NM, 40001)
        s = self.spectrum(lam)
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (s[1:] + s[:-1]) * np.diff(lam))])
        if cdf[-1] <= 0:
            raise ValueError(f"primary {self}: no power in {RANGE_NM[0]:g}..{RANGE_NM[1]:g} nm")
        cdf /= cdf[-1]
        return np.interp(np.asarray(q, dtype=np.float64), cdf, lam)


#: Colour OLED microdisplay primaries (see the module docstring for their source).
DEFAULT_PRIMARIES = {"R": Primary(620.0, 35.0), "G": Primary(530.0, 30.0), "B": Primary(460.0, 25.0)}


#: Linear sRGB from CIE 1931 XYZ (IEC 61966-2-1, D65 white).
XYZ_TO_SRGB = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])

_NATURAL: dict | None = None


def natural_primaries() -> dict:
    """The channel spectra of the natural view: a broadband (equal-energy) scene seen through
    the sRGB colour-matching functions, ``S_c(λ) = max(0, (M · [x̄, ȳ, z̄](λ))_c)``, with
    :data:`XYZ_TO_SRGB` and the CIE 1931 2° observer (Mitsuba's ``cie1931_xyz``: the CIE
    table, linearly interpolated), tabulated every nm over :data:`RANGE_NM`.

    A real scene is not three narrow primaries: a white object sends every wavelength, and
    the eye weighs them by its sensitivities. Channel medians 606 / 540 / 450 nm; the
    luminance-weighted focus of such a target is the eye's focus near 555 nm, so a natural
    target's accommodation response is its depth (:mod:`lfsim.vision.accommodation`).
    """
    global _NATURAL
    if _NATURAL is None:
        from . import mitsuba

        mi = mitsuba()
        lam = np.arange(RANGE_NM[0], RANGE_NM[1] + 0.5, 1.0)
        xyz = mi.cie1931_xyz(from_numpy(mi.Float, lam.astype(np.float32)))
        X = np.array([np.asarray(xyz[i], dtype=np.float64) for i in range(3)])
        S = np.maximum(XYZ_TO_SRGB @ X, 0.0)
        _NATURAL = {c: Primary(wavelengths_nm=tuple(lam), values=tuple(S[k] / S[k].max()))
                    for k, c in enumerate(CHANNELS)}
    return _NATURAL


@dataclass(frozen=True)
class Wavelengths:
    """The wavelength nodes of one render pass: ``nm`` (J,), picked uniformly per ray, and the
    display ``channel`` (0, 1, 2 = R, G, B) the pass renders, or None: every channel (a
    monochrome render, today's geometric image at one wavelength)."""

    nm: tuple[float, ...]
    channel: int | None = None

    @property
    def count(self) -> int:
        return len(self.nm)

    def props(self) -> dict:
        """Mitsuba plugin properties (a plain string: a property holds no arrays)."""
        return {"wavelengths": ",".join(repr(float(v)) for v in self.nm)}

    @classmethod
    def from_props(cls, props) -> Wavelengths | None:
        if "wavelengths" not in props:
            return None
        return cls(tuple(float(v) for v in str(props["wavelengths"]).split(",")))


def primaries_doc(primaries: dict | None = None) -> dict:
    """The spectra a spectral render used, JSON-ready: ``{"source": "content" | "default",
    "R": {...}, "G": {...}, "B": {...}, "natural": ...}``, each display channel its definition
    (``peak_nm``, ``fwhm_nm``, or ``wavelengths_nm`` and ``values``) and ``median_nm``;
    ``natural``: the natural view's channels (:func:`natural_primaries`), their medians."""
    prim = primaries or DEFAULT_PRIMARIES
    out: dict = {"source": "content" if primaries else "default"}
    for c in CHANNELS:
        p = prim[c]
        d = ({"peak_nm": p.peak_nm, "fwhm_nm": p.fwhm_nm} if p.wavelengths_nm is None
             else {"wavelengths_nm": list(p.wavelengths_nm), "values": list(p.values)})
        d["median_nm"] = round(float(p.quantiles([0.5])[0]), 3)
        out[c] = d
    nat = natural_primaries()
    out["natural"] = {"spectra": "equal-energy white through the sRGB colour-matching functions (CIE 1931)",
                      **{f"{c}_median_nm": round(float(nat[c].quantiles([0.5])[0]), 3) for c in CHANNELS}}
    return out


def describe(passes: list[Wavelengths]) -> str:
    """One line on a render's passes (:func:`spectral` or :func:`monochrome`)."""
    if len(passes) == 1 and passes[0].channel is None:
        return f"monochrome {passes[0].nm[0]:g} nm"
    nm = [v for p in passes for v in p.nm]
    return (f"spectral, {passes[0].count} wavelength(s) per primary ({min(nm):.0f}-{max(nm):.0f} nm), "
            f"one pass per primary")


def monochrome(wavelength_nm: float) -> list[Wavelengths]:
    """One pass, every channel at ``wavelength_nm``."""
    v = float(wavelength_nm)
    if not (math.isfinite(v) and RANGE_NM[0] <= v <= RANGE_NM[1]):
        raise ValueError(f"wavelength_nm = {wavelength_nm!r}: must lie in {RANGE_NM[0]:g}..{RANGE_NM[1]:g} nm")
    return [Wavelengths((v,))]


def spectral(samples: int = 4, primaries: dict | None = None) -> list[Wavelengths]:
    """One pass per primary (R, G, B), ``samples`` nodes each: the medians of equal-power strata."""
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1:
        raise ValueError(f"wavelength samples = {samples!r}: must be an integer >= 1")
    primaries = primaries or DEFAULT_PRIMARIES
    q = (np.arange(samples) + 0.5) / samples
    return [Wavelengths(tuple(float(v) for v in primaries[name].quantiles(q)), c)
            for c, name in enumerate(CHANNELS)]


def node_index(T, sample1, count: int):
    """Dr.Jit: the node (UInt32) of each ray's wavelength sample in [0, 1)."""
    import drjit as dr

    if count == 1:
        return dr.zeros(T.UInt32, dr.width(sample1))
    return T.UInt32(dr.minimum(dr.floor(sample1 * float(count)), float(count - 1)))
