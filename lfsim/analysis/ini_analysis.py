"""`lfsim analyze`: the paper's metrics over every sampled sub-system, with plots.

One fused trace (see :mod:`lfsim.ini.subsystems`) carries, per sub-system and
field, the chief ray, the four marginal rays of Eq. (12), two Gauss–Legendre
pupil rules (n and 2n nodes per axis: the figure and its convergence check),
the stop's perimeter (footprints) and the FFT grid of the diffraction MTF.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..ini.model import IniModel
from ..ini.package import package as ini_package
from ..ini.subsystems import Bundle, Subsystems, display_points, sample, trace, trace_many
from ..metrics import distortion, footprint, mtf, pupil, spot
from ..progress import phase

CPD_TO_CPR = 180.0 / math.pi


@dataclass
class PupilSets:
    rho: np.ndarray
    slices: dict
    weights: dict

    @classmethod
    def build(cls, n_gl: int, n_mtf: int, per_side: int = 8):
        parts = {"chief": np.zeros((1, 2)), "marginal": pupil.MARGINAL}
        weights = {}
        for name, n in (("gl", n_gl), ("gl2", 2 * n_gl)):
            nodes, w = pupil.gauss_legendre_square(n)
            parts[name], weights[name] = nodes, w
        parts["perimeter"] = pupil.perimeter(per_side)
        parts["mtf"] = pupil.mtf_grid(n_mtf)
        slices, start = {}, 0
        for k, v in parts.items():
            slices[k] = slice(start, start + len(v))
            start += len(v)
        return cls(np.concatenate(list(parts.values())), slices, weights)

    def subset(self, names) -> PupilSets:
        """Only the named sample sets (same samples and weights), e.g. what one metric needs."""
        slices, start = {}, 0
        for k in names:
            n = self.slices[k].stop - self.slices[k].start
            slices[k] = slice(start, start + n)
            start += n
        rho = np.concatenate([self.rho[self.slices[k]] for k in names])
        return PupilSets(rho, slices, {k: w for k, w in self.weights.items() if k in slices})


def opd_method(model: IniModel) -> str:
    """"opl" (traced optical path) unless the path holds an ideal (paraxial) element,
    whose optical path is exact only for one conjugate: then "slopes" (wavefront
    integrated from the ray directions, :func:`lfsim.metrics.mtf.wavefront_from_slopes`)."""
    surf = model.system.surfaces[:model.spec.viewing_window + 1]
    return "slopes" if any(s.interaction == "paraxial" for s in surf) else "opl"


def _paraxial(model: IniModel, subs, rho: np.ndarray) -> np.ndarray:
    """Paraxial viewing-window states (S, F, R, 4) of the rays (display, lenslet, rho)."""
    S, F = subs.display.shape[:2]
    out = np.empty((S, F, len(rho), 4))
    for k in np.unique(subs.k):
        sel = subs.k == k
        s = np.broadcast_to(subs.display[sel][:, :, None, :], (sel.sum(), F, len(rho), 2))
        c = np.broadcast_to(subs.center[sel][:, None, None, :], s.shape)
        r = np.broadcast_to(rho[None, None], s.shape)
        out[sel] = model.paraxial_vw(int(k), s, c, r)
    return out


def evaluate(model: IniModel, subs=None, progress: bool = False, mtf_freqs_cpd=None,
             reference: IniModel | None = None, refine: int | None = None, bundle: Bundle | None = None) -> dict:
    """Trace and measure; returns a dict of numpy arrays and the summary (see :func:`analyze`).

    ``reference``: the nominal design's model. By default a design is its own
    paraxial reference, linearized about its own axis ray, so a uniform
    deflection (a decentred or tilted element, a pupil tilt) moves the
    reference with the rays and GD/PA do not see it. With a reference, the
    display layout (EI centres, ``subs`` when not given), the paraxial rays of
    GD (Eq. 11) and PA (Eq. 12) and the footprint width d_v are the nominal
    design's, as in a tolerance analysis of built hardware that shows the
    nominal elemental images. The CDP depths of both must match.

    ``refine``: levels of the worst-contrast search of :func:`refine_contrast`
    (default the design's ``[ini.analysis] refine``; 0: the field grid only).

    ``bundle``: the rays of ``subs`` already traced (by
    :func:`lfsim.ini.subsystems.trace_many`, several designs in one launch)
    with the pupil samples of :meth:`PupilSets.build` for this design's
    ``[ini.analysis]``; they are then not traced again.
    """
    spec = model.spec
    ref = model if reference is None else reference
    if reference is not None and (len(ref.depths) != len(model.depths)
                                  or not np.allclose(ref.depths, model.depths)):
        raise ValueError(f"the reference {ref.file} has CDP depths {ref.depths}, "
                         f"the design {model.file} has {model.depths}")
    subs = subs if subs is not None else sample(ref)
    sets = PupilSets.build(spec.pupil, spec.mtf_grid)
    t0 = time.perf_counter()
    bar = None
    if progress:
        from ..progress import bar as tqdm

        bar = tqdm(total=len(subs), desc="sub-systems", unit="sub", leave=False)
    if bundle is None:
        bundle = trace(model, subs, sets.rho, progress=bar.update if bar else None)
    elif bundle.subs is not subs or not np.array_equal(bundle.rho, sets.rho):
        raise ValueError("evaluate: the bundle was traced for other sub-systems or pupil samples")
    if bar:
        bar.close()
    t_trace = time.perf_counter() - t0
    states = [ref.state(k) for k in range(len(ref.depths))]
    nyq = max(s.nyquist_cpd for s in states)
    freqs_cpd = np.asarray(mtf_freqs_cpd if mtf_freqs_cpd is not None
                           else np.linspace(0.0, 1.5 * nyq, 31), dtype=np.float64)
    freqs_cpd = np.union1d(freqs_cpd, [nyq])
    i_nyq = int(np.argmin(np.abs(freqs_cpd - nyq)))

    D = np.array(model.depths)[subs.k]  # (S,)
    ok = bundle.ok
    r = spot.retinal_tan(bundle.pos, bundle.slopes(), D[:, None, None])
    par = _paraxial(ref, subs, sets.rho)
    r_par = par[..., 2:4] - par[..., 0:2] * (D[:, None, None, None] / 1000.0)
    sl = sets.slices
    if not np.allclose(subs.fields[0], 0.0):
        raise ValueError("the first field must be the EI centre (0, 0): GD (Eq. 11) is measured there")

    # GD (Eq. 11): chief ray of the EI's centre field (field 0).
    chief_ok = ok[:, :, sl["chief"]][..., 0]
    gd = distortion.gd_deg(r[:, 0, sl["chief"]][:, 0], r_par[:, 0, sl["chief"]][:, 0])
    local = distortion.local_distortion(r[:, :, sl["chief"]][:, :, 0], r_par[:, :, sl["chief"]][:, :, 0])
    # PA (Eq. 12): four marginal rays per field.
    d_v = np.array([np.mean(states[k].d_v) for k in subs.k])
    marg_ok = np.all(ok[:, :, sl["marginal"]], axis=-1)
    pa = footprint.pa(bundle.pos[:, :, sl["marginal"]], par[:, :, sl["marginal"], 0:2], d_v[:, None])
    pa_shape = footprint.pa_shape(bundle.pos[:, :, sl["marginal"]], par[:, :, sl["marginal"], 0:2], d_v[:, None])
    # RMS spot and geometric MTF (quadrature), with the convergence check n → 2n.
    rms, cen, off = spot.rms_spot(r[:, :, sl["gl2"]], sets.weights["gl2"], ok[:, :, sl["gl2"]])
    rms_n, _, _ = spot.rms_spot(r[:, :, sl["gl"]], sets.weights["gl"], ok[:, :, sl["gl"]])
    geo = mtf.geometric_mtf(off, sets.weights["gl2"], ok[:, :, sl["gl2"]], freqs_cpd * CPD_TO_CPR)
    with phase("wavefronts and diffraction MTFs"):
        opd, dif = _diffraction(model, bundle, sets, r, cen, D, freqs_cpd)
    contrast = np.min(dif[..., i_nyq, :], axis=-1)
    g = sl["mtf"]
    wf_rms = np.sqrt(np.sum(np.where(ok[:, :, g], opd, 0) ** 2, axis=-1)
                     / np.maximum(np.sum(ok[:, :, g], axis=-1), 1)) / (model.lam * 1e-6)
    vignetted = 1.0 - np.mean(ok[:, :, sl["gl2"]], axis=-1)
    res = dict(model=model, subs=subs, sets=sets, bundle=bundle, states=states, r=r, r_par=r_par,
               cen=cen, par=par, gd=gd, local=local, pa=pa, pa_shape=pa_shape, pa_ok=marg_ok, chief_ok=chief_ok,
               rms=rms, rms_n=rms_n,
               geo=geo, dif=dif, contrast=contrast, wf_rms=wf_rms, vignetted=vignetted,
               freqs_cpd=freqs_cpd, nyquist_cpd=nyq, i_nyq=i_nyq, t_trace=t_trace)
    levels = spec.refine if refine is None else int(refine)
    with phase("searching each sub-system's worst contrast"):
        res["refined"] = refine_contrast(model, res, levels, ref) if levels > 0 else None
    res["t_all"] = time.perf_counter() - t0
    return res


def _diffraction(model: IniModel, bundle: Bundle, sets: PupilSets, r, cen, D, freqs_cpd, otf: bool = False):
    """Wavefront (mm) over the stop's FFT grid and the diffraction MTF at ``freqs_cpd`` (…, freq,
    orientation); ``otf``: the complex OTF instead, its phase referred to the image point ``cen``."""
    ok, g = bundle.ok, sets.slices["mtf"]
    opd, pup, _ = mtf.reference_opd(bundle.pos[:, :, g], bundle.dir[:, :, g], bundle.opl[:, :, g],
                                    ok[:, :, g], cen, D[:, None])
    if opd_method(model) == "slopes":
        off_g = spot.angular_offsets(r[:, :, g], cen)
        opd = mtf.wavefront_from_slopes(sets.rho[g], pup, off_g, ok[:, :, g])
    freqs = np.asarray(freqs_cpd, dtype=np.float64).ravel() * CPD_TO_CPR
    if len(freqs) == 1:  # one frequency (Nyquist): the autocorrelation summed there, not by FFT
        dif = mtf.diffraction_otf_at(sets.rho[g], pup, opd, ok[:, :, g], model.lam, float(freqs[0]))[..., None, :]
        return opd, (dif if otf else np.abs(dif))
    fn = mtf.diffraction_otf if otf else mtf.diffraction_mtf
    dif = fn(sets.rho[g], pup, opd, ok[:, :, g], model.lam, freqs)
    return opd, dif


def focus_offsets(half_range_d: float, step_d: float) -> np.ndarray:
    """The eye-focus offsets of :func:`through_focus`: −half … +half in steps of ``step`` D
    (0 always among them: the sweep is symmetric about each state's CDP)."""
    n = int(round(half_range_d / step_d))
    return step_d * np.arange(-n, n + 1, dtype=np.float64)


def _peaks(offsets: np.ndarray, curves: np.ndarray):
    """Per curve (T, ...) the position and height of its maximum, refined by the parabola
    through the largest sample and its two neighbours (a maximum on the sweep's edge is left
    there and flagged). Curves that are 0 everywhere (no pupil left) have no peak: NaN."""
    T = len(offsets)
    i = np.argmax(curves, axis=0)
    top = np.take_along_axis(curves, i[None], axis=0)[0]
    lo = np.take_along_axis(curves, np.clip(i - 1, 0, T - 1)[None], axis=0)[0]
    hi = np.take_along_axis(curves, np.clip(i + 1, 0, T - 1)[None], axis=0)[0]
    edge = (i == 0) | (i == T - 1)
    den = lo - 2.0 * top + hi
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(~edge & (den < 0), 0.5 * (lo - hi) / den, 0.0)  # vertex, in steps: |t| <= 1/2
    step = offsets[1] - offsets[0] if T > 1 else 0.0
    pos = offsets[i] + t * step
    height = np.maximum(top - 0.25 * (lo - hi) * t, top)
    none = ~(top > 0)
    return np.where(none, np.nan, pos), np.where(none, np.nan, height), edge & ~none


def through_focus(res: dict, offsets_d) -> dict:
    """The contrast at Nyquist of every sampled field and orientation with the eye focused at
    each CDP state's depth plus ``offsets_d`` (D), the tunable lens held at the state's power.

    The rays leaving the viewing window do not depend on where the eye focuses, so nothing is
    traced again: each focus changes only the reference of the retinal directions (``t −
    h·D/1000``), the spot centroid, the reference sphere of the optical path and so the
    diffraction MTF (:func:`_diffraction`, the same as the contrast of :func:`evaluate`, which
    offset 0 reproduces exactly).

    Returns ``offsets_d`` (T,), ``contrast`` (T, S, F, 2) (axis −1: modulation along x, along
    y; the analysis's contrast is the smaller), ``best_d`` (S, F, 2), each orientation's best
    focus relative to the CDP (the parabola through the sweep's largest sample and its
    neighbours; NaN where no pupil is left), ``peak`` (S, F, 2) the contrast there, ``edge``
    (S, F, 2) peaks on the sweep's edge, and ``common_best`` / ``common_d`` (S, F): each field's
    largest contrast (the smaller orientation's) over the sweep, and the focus where.
    """
    model, subs, sets, bundle = res["model"], res["subs"], res["sets"], res["bundle"]
    off = np.asarray(offsets_d, dtype=np.float64)
    if off.ndim != 1 or len(off) < 3 or not np.all(np.diff(off) > 0) or not np.allclose(np.diff(off), off[1] - off[0]):
        raise ValueError(f"through_focus: offsets must be 3 or more evenly spaced increasing values, got {off}")
    D0 = np.array(model.depths, dtype=np.float64)[subs.k]
    ok, g2 = bundle.ok, sets.slices["gl2"]
    slopes = bundle.slopes()
    out = np.empty((len(off),) + ok.shape[:2] + (2,))
    for i, d in enumerate(off):
        D = D0 + d
        r = spot.retinal_tan(bundle.pos, slopes, D[:, None, None])
        _, cen, _ = spot.rms_spot(r[:, :, g2], sets.weights["gl2"], ok[:, :, g2])
        _, dif = _diffraction(model, bundle, sets, r, cen, D, [res["nyquist_cpd"]])
        out[i] = dif[..., 0, :]
    best, peak, edge = _peaks(off, out)
    both = np.min(out, axis=-1)
    j = np.argmax(both, axis=0)
    common = np.take_along_axis(both, j[None], axis=0)[0]
    return {"offsets_d": off, "contrast": out, "best_d": best, "peak": peak, "edge": edge,
            "common_best": common, "common_d": np.where(common > 0, off[j], np.nan)}


def _stats(v: np.ndarray) -> dict | None:
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    return {"mean": _f(np.mean(v)), "rms": _f(np.sqrt(np.mean(v * v))), "std": _f(np.std(v)),
            "min": _f(np.min(v)), "max": _f(np.max(v))}


def _through_focus_summary(tf: dict, sel: np.ndarray) -> dict:
    """``by_depth[D].through_focus`` of ``metrics.json`` for the sub-systems ``sel``."""
    c = tf["contrast"][:, sel]
    bx, by = tf["best_d"][sel, :, 0], tf["best_d"][sel, :, 1]
    both = np.isfinite(bx) & np.isfinite(by)
    each = np.min(tf["peak"][sel], axis=-1)
    return {
        "focus_offsets_d": [round(float(v), 12) for v in tf["offsets_d"]],
        "contrast_mean": [_f(v) for v in np.mean(np.min(c, axis=-1), axis=(1, 2))],
        "contrast_min": [_f(v) for v in np.min(c, axis=(1, 2, 3))],
        "best_focus_x_d": _stats(bx), "best_focus_y_d": _stats(by),
        "field_curvature_d": _stats(np.where(both, 0.5 * (bx + by), np.nan)),
        "astigmatism_d": _stats(np.where(both, bx - by, np.nan)),
        "contrast_at_best_focus": {"mean": _f(np.mean(tf["common_best"][sel])),
                                   "min": _f(np.min(tf["common_best"][sel]))},
        "contrast_each_axis_at_best_focus": {"mean": _f(np.mean(np.where(both, each, 0.0))),
                                             "min": _f(np.min(np.where(both, each, 0.0)))},
        "fields": int(np.sum(both)), "fields_without_a_peak": int(np.sum(~both)),
        "peaks_at_sweep_edge": int(np.sum(tf["edge"][sel])),  # orientation peaks (two per field)
    }


#: The eight neighbours of a field point, in units of the search step.
_NEIGHBOURS = np.array([(-1, -1), (0, -1), (1, -1), (-1, 0), (1, 0), (-1, 1), (0, 1), (1, 1)], dtype=np.float64)


def refine_contrast(model: IniModel, res: dict, levels: int, reference: IniModel | None = None) -> dict:
    """Each EI's worst contrast at Nyquist, searched around its worst grid field.

    The field grid (``fields`` per axis) brackets the worst field of an
    elemental image; the minimum itself usually lies between grid points,
    where the prism's field-dependent astigmatism peaks. Starting at the
    grid's worst field, each level traces the 8 neighbours at half the
    previous step (the first step is half the grid spacing), clipped to the
    EI, and moves to the worst of them: after L levels the worst field is
    located to 1/2^L of the grid spacing. One fused trace per level,
    8 fields per sub-system.

    Returns
    -------
    dict
        ``contrast_min`` (S,) the smallest contrast found (≤ the grid's),
        ``field`` (S, 2) where (field fractions), ``levels``,
        ``fields_traced`` (extra fields per sub-system), ``seconds``.
    """
    ref = model if reference is None else reference
    subs, sets, spec = res["subs"], res["sets"], model.spec
    t0 = time.perf_counter()
    c = np.where(np.isfinite(res["contrast"]), res["contrast"], np.inf)
    j = np.argmin(c, axis=1)
    best = c[np.arange(len(subs)), j]
    u = subs.fields[j].copy()
    F = subs.fields.shape[0]
    nf = spec.fields if spec.fields ** 2 == F else max(int(round(F ** 0.5)), 1)
    frac = spec.field_fraction
    step = frac / (nf - 1) if nf > 1 else 0.5 * frac
    D = np.array(model.depths)[subs.k]
    nyq = np.array([res["nyquist_cpd"]])
    # The contrast needs the FFT grid and the centroid of the 2n Gauss-Legendre rule
    # (its reference point): the other pupil samples are not traced.
    sets = sets.subset(["gl2", "mtf"])
    for _ in range(levels):
        cand = np.clip(u[:, None, :] + step * _NEIGHBOURS[None], -frac, frac)  # (S, 8, 2)
        rsubs = Subsystems(subs.m, subs.n, subs.k, cand, subs.center,
                           display_points(ref, subs.m, subs.n, subs.k, cand))
        bundle = trace(model, rsubs, sets.rho)
        r = spot.retinal_tan(bundle.pos, bundle.slopes(), D[:, None, None])
        gl2 = sets.slices["gl2"]
        _, cen, _ = spot.rms_spot(r[:, :, gl2], sets.weights["gl2"], bundle.ok[:, :, gl2])
        _, dif = _diffraction(model, bundle, sets, r, cen, D, nyq)
        cc = np.min(dif[..., 0, :], axis=-1)
        cc = np.where(np.isfinite(cc), cc, np.inf)
        jj = np.argmin(cc, axis=1)
        cmin = cc[np.arange(len(subs)), jj]
        better = cmin < best
        best = np.where(better, cmin, best)
        u[better] = cand[better, jj[better]]
        step *= 0.5
    return {"contrast_min": best, "field": u, "levels": int(levels), "fields_traced": 8 * int(levels),
            "seconds": time.perf_counter() - t0}


def _f(v) -> float | None:
    v = float(v)
    return v if math.isfinite(v) else None


def _masked(fn, values, valid):
    """``fn`` over the valid entries; None when there are none (a failed ray has no metric)."""
    v = np.asarray(values)[np.asarray(valid)]
    return _f(fn(v)) if v.size else None


def contrast_min(res: dict) -> np.ndarray:
    """(S,) each sub-system's worst contrast at Nyquist: the refined search's when it ran, else the grid's."""
    grid = np.min(res["contrast"], axis=1)
    refined = res.get("refined")
    return grid if refined is None else np.minimum(grid, refined["contrast_min"])


def lateral_colour(model: IniModel, subs: Subsystems) -> dict | None:
    """Lateral colour of every sampled field: ``{"wavelengths_nm": [short, long], "arcmin": (S, F),
    "ok": (S, F)}``, or None for a design of one wavelength.

    The angle, seen from the viewing-window centre, between the image points (at the sub-system's
    CDP depth: :func:`lfsim.metrics.spot.retinal_tan`) of the same display point at the design's
    shortest and longest wavelengths (F and C for the usual 486.13 / 587.56 / 656.27 nm), each the
    chief ray through the lenslet's stop centre at its own wavelength, with the tunable lens at the
    primary wavelength's powers (it is an ideal lens: no colour of its own). The analysis proper
    runs at the primary wavelength only; this is the colour it does not see.
    """
    w = sorted(float(v) for v in model.system.wavelengths_nm)
    if len(w) < 2 or w[0] == w[-1]:
        return None
    short, long_ = trace_many([model.at_wavelength(x) for x in (w[0], w[-1])], subs, np.zeros((1, 2)))
    D = np.array(model.depths)[subs.k][:, None]
    ends = []
    for b in (short, long_):
        r = spot.retinal_tan(b.pos[:, :, 0], b.slopes()[:, :, 0], D)
        v = np.concatenate([r, np.ones(r.shape[:-1] + (1,))], axis=-1)
        ends.append(v)
    a, b = ends
    angle = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))
    ok = short.ok[:, :, 0] & long_.ok[:, :, 0]
    return {"wavelengths_nm": [w[0], w[-1]], "arcmin": np.where(ok, angle * spot.ARCMIN, np.nan), "ok": ok}


def polychromatic_contrast(res: dict) -> dict | None:
    """The contrast at Nyquist of the polychromatic diffraction MTF, per sub-system and field:
    ``{"wavelengths_nm": [...], "contrast": (S, F)}``, or None for a design of one wavelength.

    Every wavelength of ``[system] wavelengths_nm`` is traced through the same sub-systems and
    pupil grid (the tunable lens at the primary wavelength's powers, as in
    :func:`lateral_colour`); each one's wavefront is referred to the same image point, the
    primary wavelength's spot centroid, so its OTF carries its lateral shift as a phase and its
    axial colour as defocus. The OTFs are averaged with equal weights (the lens-design default)
    and the contrast is the modulus at Nyquist, the smaller of the two orientations, like the
    monochromatic ``contrast``. Lateral colour of δ between two equal wavelengths lowers the
    contrast by ``|cos(π ν δ)|``.
    """
    model, subs, sets = res["model"], res["subs"], res["sets"]
    waves = sorted({float(v) for v in model.system.wavelengths_nm})
    if len(waves) < 2:
        return None
    others = [model.at_wavelength(x) for x in waves if x != float(model.lam)]
    D = np.array(model.depths)[subs.k]
    nyq = np.array([res["nyquist_cpd"]])
    # the primary's bundle is already traced; the others in one launch
    runs = [(m, b, spot.retinal_tan(b.pos, b.slopes(), D[:, None, None]))
            for m, b in zip(others, trace_many(others, subs, sets.rho))]
    if len(others) < len(waves):
        runs.append((model, res["bundle"], res["r"]))
    total = 0.0
    for m, b, r in runs:
        total = total + _diffraction(m, b, sets, r, res["cen"], D, nyq, otf=True)[1][..., 0, :]
    return {"wavelengths_nm": waves, "contrast": np.min(np.abs(total) / len(waves), axis=-1)}


def _window_crossing(res: dict, sel: np.ndarray) -> dict | None:
    """Where the sub-systems ``sel``'s EI-centre chief rays (field 0) cross the line of sight,
    relative to the viewing window (:func:`lfsim.metrics.footprint.axis_crossing`; + toward the eye)."""
    b, ch = res["bundle"], res["sets"].slices["chief"]
    d = b.dir[sel, 0, ch][:, 0]
    return footprint.axis_crossing(b.pos[sel, 0, ch][:, 0], d[:, :2] / d[:, 2:3])


def _gd_terms(res: dict, sel: np.ndarray) -> dict | None:
    """GD's displacement field over the sub-systems ``sel`` (one CDP state) as a cubic in the
    field (:func:`lfsim.metrics.distortion.distortion_terms`): smile, keystone, scale, …"""
    ch = res["sets"].slices["chief"]
    return distortion.distortion_terms(res["r"][sel, 0, ch][:, 0], res["r_par"][sel, 0, ch][:, 0])


def summarize(res: dict, package: bool = True) -> dict:
    """The ``metrics.json`` document (the contract in docs/contracts.md plus per-sub-system details).

    GD needs the centre field's chief ray and PA a field's four marginal rays;
    where those failed (vignetted, crosstalk) the value is left out of every
    statistic and reported as null, and the failures are counted.
    ``package``: also the design's mechanical package (:func:`lfsim.ini.package.package`,
    about 0.1 s; a caller that reads only the summary can leave it out).
    """
    model, subs, spec = res["model"], res["subs"], res["model"].spec
    arcmin = spot.ARCMIN
    lc = res.get("lateral_colour")
    poly = res.get("polychromatic")
    pc = poly["contrast"] if poly else None
    tf = res.get("through_focus")
    pa_ok, gd_ok = res["pa_ok"], res["chief_ok"][:, 0]
    pa_sub = np.max(np.where(pa_ok, res["pa"], -np.inf), axis=1)
    sub_ok = np.any(pa_ok, axis=1)
    c_min = contrast_min(res)
    refined = res.get("refined")
    subsystems = []
    for i in range(len(subs)):
        k = int(subs.k[i])
        subsystems.append({
            "m": int(subs.m[i]) + 1, "n": int(subs.n[i]) + 1, "depth_diopters": model.depths[k],
            "gd_deg": _f(res["gd"][i]) if gd_ok[i] else None,
            "pa_max": _f(pa_sub[i]) if sub_ok[i] else None,
            "pa_mean": _masked(np.mean, res["pa"][i], pa_ok[i]),
            "pa_shape_max": _masked(np.max, res["pa_shape"][i], pa_ok[i]),
            "contrast_nyquist": _f(c_min[i]),
            "contrast_nyquist_fields": [_f(v) for v in res["contrast"][i]],
            "contrast_nyquist_worst_field": [_f(v) for v in refined["field"][i]] if refined else None,
            "contrast_nyquist_poly_fields": [_f(v) for v in pc[i]] if poly else None,
            "rms_spot_arcmin": [_f(v * arcmin) for v in res["rms"][i]],
            "local_distortion_pct_max": _f(100 * np.max(res["local"][i])),
            "wavefront_rms_waves": [_f(v) for v in res["wf_rms"][i]],
            "vignetted_fraction": [_f(v) for v in res["vignetted"][i]],
            "lateral_colour_arcmin": ([_f(v) if o else None for v, o in zip(lc["arcmin"][i], lc["ok"][i])]
                                      if lc else None),
            "best_focus_offset_d": ([[_f(v) for v in field] for field in tf["best_d"][i]] if tf else None),
            "chief_ray_ok": bool(res["chief_ok"][i, 0]),
            "marginal_rays_ok": bool(np.all(res["pa_ok"][i])),
        })
    by_depth = {}
    for k, D in enumerate(model.depths):
        sel = subs.k == k
        if not np.any(sel):
            continue
        c = res["contrast"][sel]
        by_depth[f"{D:g}"] = {
            "contrast_nyquist_min": _f(np.min(c_min[sel])), "contrast_nyquist_mean": _f(np.mean(c)),
            "contrast_nyquist_poly_min": _f(np.min(pc[sel])) if poly else None,
            "contrast_nyquist_poly_mean": _f(np.mean(pc[sel])) if poly else None,
            "rms_spot_mean_arcmin": _f(np.mean(res["rms"][sel]) * arcmin),
            "rms_spot_max_arcmin": _f(np.max(res["rms"][sel]) * arcmin),
            "gd_max_deg": _masked(np.max, res["gd"][sel], gd_ok[sel]),
            "gd_mean_deg": _masked(np.mean, res["gd"][sel], gd_ok[sel]),
            "pa_max": _masked(np.max, pa_sub[sel], sub_ok[sel]),
            "pa_mean": _masked(np.mean, res["pa"][sel], pa_ok[sel]),
            "pa_shape_max": _masked(np.max, res["pa_shape"][sel], pa_ok[sel]),
            "viewing_window_real": _window_crossing(res, sel & gd_ok),
            "gd_terms": _gd_terms(res, sel & gd_ok),
            "lateral_colour_max_arcmin": _masked(np.max, lc["arcmin"][sel], lc["ok"][sel]) if lc else None,
            "lateral_colour_mean_arcmin": _masked(np.mean, lc["arcmin"][sel], lc["ok"][sel]) if lc else None,
            "through_focus": _through_focus_summary(tf, sel) if tf else None,
            "first_order": res["states"][k].as_dict(),
        }
    conv = np.abs(res["rms"] - res["rms_n"])
    summary = {
        "gd_max_deg": _masked(np.max, res["gd"], gd_ok), "gd_mean_deg": _masked(np.mean, res["gd"], gd_ok),
        "pa_max": _masked(np.max, pa_sub, sub_ok), "pa_mean": _masked(np.mean, res["pa"], pa_ok),
        "pa_within_target": int(np.sum(sub_ok & (pa_sub <= spec.pa_target))), "pa_target": spec.pa_target,
        "pa_shape_max": _masked(np.max, res["pa_shape"], pa_ok),
        "pa_shape_mean": _masked(np.mean, res["pa_shape"], pa_ok),
        "gd_within_target": int(np.sum(gd_ok & (res["gd"] <= spec.gd_target_deg))),
        "gd_target_deg": spec.gd_target_deg,
        "gd_failed": int(np.sum(~gd_ok)), "pa_fields_failed": int(np.sum(~pa_ok)),
        "subsystems_evaluated": len(subs),
        "lenslets_evaluated": len({(int(a), int(b)) for a, b in zip(subs.m, subs.n)}),
        "fields_per_subsystem": int(subs.fields.shape[0]), "nyquist_cpd": _f(res["nyquist_cpd"]),
        "contrast_nyquist_min": _f(np.min(c_min)), "contrast_nyquist_mean": _f(np.mean(res["contrast"])),
        "contrast_nyquist_min_grid": _f(np.min(res["contrast"])),
        "contrast_nyquist_poly_min": _f(np.min(pc)) if poly else None,
        "contrast_nyquist_poly_mean": _f(np.mean(pc)) if poly else None,
        "contrast_poly_wavelengths_nm": poly["wavelengths_nm"] if poly else None,
        "contrast_refine_levels": refined["levels"] if refined else 0,
        "contrast_refine_s": round(refined["seconds"], 3) if refined else 0.0,
        "rms_spot_mean_arcmin": _f(np.mean(res["rms"]) * arcmin),
        "lateral_colour_max_arcmin": _masked(np.max, lc["arcmin"], lc["ok"]) if lc else None,
        "lateral_colour_mean_arcmin": _masked(np.mean, lc["arcmin"], lc["ok"]) if lc else None,
        "lateral_colour_wavelengths_nm": lc["wavelengths_nm"] if lc else None,
        "local_distortion_pct_max": _f(100 * np.max(res["local"])),
        "rays_failed": int(np.sum(~res["bundle"].ok[:, :, res["sets"].slices["gl2"]])),
        "rms_spot_quadrature_error_arcmin": _f(np.max(conv) * arcmin),
        "aim_error_mm": _f(res["bundle"].aim_error),
        "rays_traced": int(res["bundle"].status.size),
        "trace_s": round(res["t_trace"], 3), "wall_s": round(res["t_all"], 3),
    }
    doc = {"design": model.design.name, "file": model.file, "wavelength_nm": model.lam,
           "summary": summary, "by_depth": by_depth, "subsystems": subsystems,
           "mtf_frequencies_cpd": [float(v) for v in res["freqs_cpd"]]}
    if package:
        doc["package"] = ini_package(model)
    return doc


def analyze(design, out_dir=None, stride=None, symmetry=None, depths_diopters=None,
            progress: bool = False, plots: bool = True, reference=None, polychromatic: bool = False,
            through_focus_d: tuple[float, float] | None = None) -> dict:
    """Evaluate every sampled sub-system and write ``metrics.json`` and the plots.

    ``depths_diopters`` restricts the CDP states (values from the design's
    list). ``reference``: a nominal Design whose display layout and paraxial
    rays GD and PA are measured against (see :func:`evaluate`). ``polychromatic``: also the
    contrast of the polychromatic MTF (:func:`polychromatic_contrast`; it traces and
    transforms every wavelength, about twice the time of the rest, so it is off by
    default). ``through_focus_d``: (half range, step) in diopters of an eye-focus sweep about
    each state's CDP (:func:`through_focus`: each field's and orientation's best focus, the
    field curvature and astigmatism it gives, and the contrast at it). Returns the
    metrics document (also written to ``out_dir``, a folder replaced as a
    whole on success: see :func:`lfsim.fileio.atomic_dir`).
    """
    from ..fileio import atomic_dir, check_replaceable, write_json
    from . import ini_plots

    if out_dir is not None:
        check_replaceable(out_dir, "metrics.json")
    model = IniModel(design)
    ref = IniModel(reference) if reference is not None else model
    depths = None
    if depths_diopters is not None:
        depths = []
        for D in depths_diopters:
            hit = [k for k, v in enumerate(model.depths) if abs(v - D) < 1e-9]
            if not hit:
                raise ValueError(f"--depths: {D:g} D is not a CDP depth of {model.file} "
                                 f"({', '.join(f'{v:g}' for v in model.depths)})")
            depths.append(hit[0])
    subs = sample(ref, stride=stride, symmetry=symmetry, depths=depths)
    res = evaluate(model, subs, progress=progress, reference=None if ref is model else ref)
    t0 = time.perf_counter()
    with phase("tracing the lateral colour"):
        res["lateral_colour"] = lateral_colour(model, subs)
    if polychromatic and progress:
        from ..progress import line

        line(f"polychromatic contrast: tracing {len(subs)} sub-systems at "
             f"{len(set(model.system.wavelengths_nm)) - 1} more wavelengths")
    with phase("the polychromatic contrast"):
        res["polychromatic"] = polychromatic_contrast(res) if polychromatic else None
    if through_focus_d is not None:
        offsets = focus_offsets(*through_focus_d)
        if progress:
            from ..progress import line

            line(f"through focus: {len(offsets)} eye foci from {offsets[0]:+g} to {offsets[-1]:+g} D "
                 f"about each CDP, {len(subs)} sub-systems")
        with phase("the through-focus contrast"):
            res["through_focus"] = through_focus(res, offsets)
    res["t_all"] += time.perf_counter() - t0  # the wall time includes colour's extra traces
    with phase("measuring the package"):
        doc = summarize(res)
    if ref is not model:
        doc["reference"] = ref.file
    if out_dir is not None:
        with atomic_dir(out_dir, "metrics.json") as out:
            if plots:
                with phase("drawing the plots"):
                    doc["plots"] = ini_plots.write_all(res, out)
            doc["summary"]["wall_s"] = round(res["t_all"], 3)
            write_json(out / "metrics.json", doc)
    return doc
