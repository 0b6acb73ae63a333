"""Error against run time of every approximation knob (the accuracy report).

Each knob (a setting that trades accuracy for run time) is swept on shipped
designs; every setting's error is measured against a converged reference (a
setting far beyond the default, or an exact answer) and its run time on this
machine. The knobs, by stage:

* tracer (:class:`lfsim.optics.tracer.SequentialTracer`): precision (float32 or
  float64), Newton tolerance and Newton iteration cap of the aspheric/freeform
  intersection; error = largest ray-position difference at the last surface
  against a float64 trace with a tight tolerance, plus the share of rays whose
  status differs (e.g. flagged ``not_converged``);
* metrics (:func:`lfsim.analysis.ini_analysis.evaluate`): the pupil quadrature
  (RMS spot, geometric MTF), the FFT pupil grid (diffraction MTF, contrast at
  Nyquist), the field grid per elemental image (PA, contrast) and the lenslet
  stride (GD and PA over the whole display), each against its densest setting
  (all lenslets for the stride, which is exact);
* render (:func:`lfsim.render.accuracy.error_vs_time`): samples per pixel of
  the analytic path against a high-spp render, and the mesh tessellation
  against the analytic path with the same eye rays; the wavelength nodes per
  primary (:func:`lfsim.render.accuracy.wavelength_error`); the retinal
  cameras' sampler against Mitsuba's, at the default focal stack's size
  (:func:`lfsim.render.accuracy.sampler_noise`);
* eye (:func:`lfsim.render.eye_models.solve_accommodation`): the Arizona eye's
  accommodation solve (criterion, minimizer tolerance, pupil rings) against a
  tight solve.

Each knob's default is read from the code that sets it; the report states
where, the error and time at the default, an accuracy target with its reason,
and the cheapest setting that meets it. Everything is written atomically:
``accuracy.md`` and ``img/accuracy_<knob>.png`` under the output folder
(``docs/`` by default), and the figures to
``benchmarks/results/accuracy_report.json``.

    .venv/bin/python benchmarks/accuracy_report.py [--quick] [--out DIR] [--json]

The measurements use the library's public pieces only (the tracer, the InI
analysis, ``lfsim.render.accuracy.error_vs_time``, the eye model's
accommodation solve); this file holds the sweep settings, the targets and
the prose.
"""

from __future__ import annotations

import copy
import inspect
import math
import os
import platform
import sys
import textwrap
import time
from dataclasses import asdict, dataclass, field, replace
from datetime import UTC
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
SCENES = ROOT / "scenes"
CONTRAST_WHY = ("0.01: the last digit of the contrasts the method states (reference/ini-hmd-design-method.txt, "
                "Section 6: threshold 0.2, mean 0.53)")
PA_WHY = ("0.001: the last digit of the PA values the method states (reference/ini-hmd-design-method.txt, "
          "Section 4: PA 0.059 and 0.23)")
ARCMIN = 60.0 * 180.0 / math.pi


@dataclass
class Target:
    """The accuracy a knob must reach: ``errors[index] <= value``, and why."""

    index: int
    value: float
    why: str


@dataclass
class Knob:
    """One approximation knob: its settings' errors and run times, per series (design)."""

    key: str
    stage: str
    title: str
    setting: str  # column header of the setting
    errors: list[str]  # error column headers (with units)
    reference: str  # what the errors are measured against
    timing: str  # what the seconds measure
    default: object  # the default setting, read from the code
    default_source: str  # where lfsim sets it
    targets: list[Target]  # every targeted error must meet its bound (empty: no target)
    rows: list[dict] = field(default_factory=list)  # {series, setting, label, errors, seconds}
    notes: list[str] = field(default_factory=list)
    extra: dict = field(default_factory=dict)

    def add(self, series: str, setting, errors, seconds: float, label: str | None = None):
        self.rows.append({"series": series, "setting": setting, "label": label or _label(setting),
                          "errors": [None if e is None else float(e) for e in errors], "seconds": float(seconds)})

    def series(self) -> list[str]:
        return list(dict.fromkeys(r["series"] for r in self.rows))

    def default_rows(self) -> list[dict]:
        return [r for r in self.rows if r["setting"] == self.default]


def _label(v) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (tuple, list)):
        return ",".join(_label(x) for x in v)
    return str(v)


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "—"
    if v == 0:
        return "0"
    return f"{v:.{digits}g}"


def _maxdiff(a, b, scale: float = 1.0) -> float | None:
    """max |a − b| (× scale) over the entries finite in both; None if there are none."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.max(np.abs(a[ok] - b[ok])) * scale) if np.any(ok) else None


def _best_time(fn, repeats: int) -> tuple[object, float]:
    """(result, best seconds of ``repeats`` calls) after one untimed warm-up call (kernel compilation)."""
    out = fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return out, best


# ===================================================================== tracer
def _conventional_rays(design, n: int, seed: int = 0):
    """``n`` rays uniform over the entrance pupil disc, cycling through the design's fields."""
    from lfsim.optics.sampling import field_rays

    fo = design.first_order()
    rng = np.random.default_rng(seed)
    r, a = np.sqrt(rng.random(n)), 2.0 * math.pi * rng.random(n)
    pupil = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    which = np.arange(n) % len(design.system.fields)
    O, D = np.empty((n, 3)), np.empty((n, 3))
    for i, f in enumerate(design.system.fields):
        sel = which == i
        O[sel], D[sel] = field_rays(design.system, fo, f, pupil[sel])
    return O, D


def _display_rays(design, n: int, seed: int = 0):
    """``n`` rays from uniform display points to uniform points of their lenslet's cell (InI designs)."""
    arr = design.system.arrays[design.ini.mla]
    g = design.system.object_distance
    rng = np.random.default_rng(seed)
    p = np.array(arr.pitch)
    s = (rng.random((n, 2)) - 0.5) * p * [arr.m, arr.n] + arr.center
    idx = np.clip(np.floor((s - arr.center) / p + 0.5 * np.array([arr.m, arr.n])), 0, [arr.m - 1, arr.n - 1])
    c = arr.center + (idx - 0.5 * (np.array([arr.m, arr.n]) - 1)) * p
    tgt = c + (rng.random((n, 2)) - 0.5) * 0.98 * p
    o = np.column_stack([s, np.full(n, -g)])
    d = np.column_stack([tgt - s, np.full(n, g)])
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _trace(design, O, D, repeats: int, precision: str = "float64", **kw):
    """Positions (N, 3), status (N,) and best seconds of a full trace of the rays."""
    import drjit as dr

    from lfsim.optics.tracer import SequentialTracer

    tr = SequentialTracer(design.system, precision, **kw)
    P, rays = tr.params(), tr.rays(O, D)

    def run():
        with dr.suspend_grad():
            out = tr.trace(P, rays)
            dr.eval(out.p, out.d, out.status, out.opl)
            dr.sync_thread()
        return out

    out, secs = _best_time(run, repeats)
    pos = np.stack([np.asarray(out.p[i], dtype=np.float64) for i in range(3)], axis=1)
    return pos, np.asarray(out.status).astype(np.int64), secs, tr


def _compare(ref, got) -> tuple[float | None, float]:
    """(max |Δposition| over rays OK in both or None, fraction of rays whose status differs)."""
    (p0, s0), (p1, s1) = ref, got
    both = (s0 == 0) & (s1 == 0)
    err = float(np.max(np.abs(p1[both] - p0[both]))) if np.any(both) else None
    return err, float(np.mean(s0 != s1))


def measure_tracer(scenes: Path, quick: bool, log) -> list[Knob]:
    import lfsim
    from lfsim.optics.tracer import SequentialTracer

    sig = inspect.signature(SequentialTracer.__init__).parameters
    names = ["freeform_prism"] if quick else ["freeform_prism", "direct_view", "ini_freeform"]
    first = lfsim.load(scenes / f"{names[0]}.toml").system
    default_tol = {p: SequentialTracer(first, p).newton_tol for p in ("float64", "float32")}
    cap_default = sig["newton_max_iter"].default
    n = 20_000 if quick else 1_000_000
    repeats = 1 if quick else 3
    tols = [1e-2, 1e-6, 1e-12] if quick else [1e-1, 1e-2, 1e-4, 1e-6, 1e-8, 1e-10, 1e-12, 1e-14]
    caps = [1, 2, 3, 16] if quick else [1, 2, 3, 4, 6, 8, 16, 32]
    target = [Target(0, 1e-6, "1 nm at the image: a thousandth of a micrometre, the scale of the spot sizes and "
                     "ray positions lfsim reports"),
              Target(1, 0.0, "no ray flagged differently from the reference")]
    errs = ["max |Δposition| at the last surface (mm)", "rays with another status (fraction)"]
    ref_txt = "float64 trace with Newton tolerance 1e-14 mm and 64 iterations"
    timing = f"best of {repeats} traces of {n:.0e} rays (positions, directions, status, optical path)"
    prec = Knob("tracer_precision", "tracer", "Tracer precision", "precision", errs, ref_txt, timing,
                sig["precision"].default, "`SequentialTracer(precision=\"float64\")` (lfsim/optics/tracer.py); "
                "the render path traces in float32 (`ReverseOptics(precision=\"float32\")`, lfsim/render/analytic.py)",
                target)
    ntol = Knob("newton_tol", "tracer", "Newton tolerance (float64)", "tolerance |Δt| (mm)", errs, ref_txt, timing,
                default_tol["float64"], f"`SequentialTracer(newton_tol=None)`: {default_tol['float64']:g} mm in "
                f"float64, {default_tol['float32']:g} mm in float32 (lfsim/optics/tracer.py)", target)
    ncap = Knob("newton_max_iter", "tracer", "Newton iteration cap (float64)", "iterations", errs, ref_txt, timing,
                cap_default, f"`SequentialTracer(newton_max_iter={cap_default})` (lfsim/optics/tracer.py)", target)
    for name in names:
        design = lfsim.load(scenes / f"{name}.toml")
        O, D = _display_rays(design, n) if design.ini is not None else _conventional_rays(design, n)
        if design.ini is not None:
            prec.extra.setdefault("pixel_pitch", {})[name] = design.ini.pixel_pitch
        log(f"  tracer: {name}, {n:.0e} rays")
        p_ref, s_ref, _, _ = _trace(design, O, D, 0, "float64", newton_tol=1e-14, newton_max_iter=64)
        ref = (p_ref, s_ref)
        for p in ("float64", "float32"):
            pos, st, secs, _ = _trace(design, O, D, repeats, p)
            prec.add(name, p, _compare(ref, (pos, st)), secs)
        for t in tols:
            pos, st, secs, _ = _trace(design, O, D, repeats, "float64", newton_tol=t)
            ntol.add(name, t, _compare(ref, (pos, st)), secs)
        for c in caps:
            pos, st, secs, _ = _trace(design, O, D, repeats, "float64", newton_max_iter=c)
            ncap.add(name, c, _compare(ref, (pos, st)), secs)
    for k in (prec, ntol, ncap):
        k.notes.append("Designs: " + ", ".join(names) + " (XY-polynomial prism surfaces, mirror and TIR; aspheric "
                       "lenslets). InI designs are traced from uniform display points through uniform points of their "
                       "lenslet's cell; conventional designs over the entrance pupil at every field.")
    return [prec, ntol, ncap]


# ==================================================================== metrics
def measure_metrics(scenes: Path, quick: bool, log) -> list[Knob]:
    import lfsim
    from lfsim.analysis.ini_analysis import contrast_min, evaluate
    from lfsim.design.ini_section import IniSpec
    from lfsim.ini.model import IniModel
    from lfsim.ini.subsystems import sample

    d = {f: IniSpec.__dataclass_fields__[f].default for f in ("pupil", "mtf_grid", "fields", "refine", "stride")}
    src = "`[ini.analysis] {}` (default in `IniSpec`, lfsim/design/ini_section.py)"
    names = ["ini_coaxial"] if quick else ["ini_coaxial", "ini_freeform"]
    cheap = dict(pupil=2, mtf_grid=8, refine=0)
    lenslets = [(2, 1), (4, 2)] if quick else None  # quick: the centre and a corner of a 5 × 3 array
    stride = (4, 4)
    pupils = ([2, 8], 16) if quick else ([2, 3, 4, 6, 8, 12, 16], 32)
    grids = ([8, 32], 64) if quick else ([8, 16, 24, 32, 48, 64], 128)
    fields = ([1, 3], 5) if quick else ([1, 3, 5, 9], 17)
    refines = ([0, 1, 2], 3) if quick else ([0, 1, 2, 3, 4], 4)
    strides = [(2, 2), (1, 1)] if quick else [(8, 8), (4, 4), (2, 2), (1, 1)]
    t_txt = "wall time of `evaluate` (trace and metrics) with the other sampling knobs at their cheapest " \
            f"(pupil {cheap['pupil']}, mtf_grid {cheap['mtf_grid']})"
    pupil = Knob("pupil", "metrics", "Pupil quadrature (RMS spot, geometric MTF)", "nodes n per axis "
                 "(2n used)", ["RMS spot (arcmin)", "geometric MTF at Nyquist"],
                 f"n = {pupils[1]} ({2 * pupils[1]}² Gauss–Legendre nodes)", t_txt, d["pupil"], src.format("pupil"),
                 [Target(0, 0.01, "0.01′: the last digit of the RMS spots lfsim reports (docs/ini-metrics.md)")])
    grid = Knob("mtf_grid", "metrics", "FFT pupil grid (diffraction MTF, contrast at Nyquist)", "grid per axis",
                ["contrast at Nyquist", "diffraction MTF, 0–1.5 × Nyquist"], f"a {grids[1]}² grid", t_txt,
                d["mtf_grid"], src.format("mtf_grid"),
                [Target(0, 0.01, CONTRAST_WHY)])
    ref_txt = f"{fields[1]}² fields and a {refines[1]}-level worst-contrast search"
    fld = Knob("fields", "metrics", "Field grid per elemental image (PA, contrast)", "fields per EI axis",
               ["PA max over the EI (Eq. 12)", "contrast min over the EI"], ref_txt,
               t_txt.replace("(pupil", f"(refine {d['refine']}, pupil"), d["fields"], src.format("fields"),
               [Target(0, 0.001, PA_WHY), Target(1, 0.01, CONTRAST_WHY)])
    rfn = Knob("refine", "metrics", "Worst-contrast search between fields", "levels (8 fields each)",
               ["contrast min over the EI"], ref_txt, t_txt.replace("(pupil", f"(fields {d['fields']}, pupil"),
               d["refine"], src.format("refine"), [Target(0, 0.01, CONTRAST_WHY)])
    strd = Knob("stride", "metrics", "Lenslet stride (GD and PA over the display)", "stride", ["GD max (deg)",
                "PA max"], "every lenslet (stride 1, 1: exact)", t_txt, tuple(d["stride"]), src.format("stride"),
                [Target(0, 0.01, "0.01°: the last digit of the GD values the method states (reference/"
                        "ini-hmd-design-method.txt, Sections 4 and 6: GD 0.36° and 0.22°)"),
                 Target(1, 0.001, PA_WHY)])
    for name in names:
        design = _reduced(scenes / f"{name}.toml", 5, 3) if quick else lfsim.load(scenes / f"{name}.toml")
        model = IniModel(design)
        k = 1 if len(model.depths) > 1 else 0
        depth = model.depths[k]
        log(f"  metrics: {name} at {depth:g} D")

        def run(stride_=stride, lens=lenslets, **kw):
            m = copy.copy(model)
            m.spec = replace(model.spec, **{**cheap, **kw})
            subs = sample(m, stride=stride_, depths=[k], lenslets=lens)
            t0 = time.perf_counter()
            res = evaluate(m, subs)
            return res, time.perf_counter() - t0

        run()  # warm-up: kernel compilation
        ref, _ = run(pupil=pupils[1])
        nyq = ref["i_nyq"]
        for n_ in pupils[0]:
            res, secs = run(pupil=n_)
            pupil.add(name, n_, [_maxdiff(res["rms"], ref["rms"], ARCMIN),
                                 _maxdiff(res["geo"][..., nyq, :], ref["geo"][..., nyq, :])], secs)
        ref, _ = run(mtf_grid=grids[1])
        for g_ in grids[0]:
            res, secs = run(mtf_grid=g_)
            grid.add(name, g_, [_maxdiff(res["contrast"], ref["contrast"]), _maxdiff(res["dif"], ref["dif"])], secs)

        def per_sub(res):
            pa = np.max(np.where(res["pa_ok"], res["pa"], -np.inf), axis=1)
            return pa, contrast_min(res)

        ref, _ = run(fields=fields[1], refine=refines[1])
        pa_ref, c_ref = per_sub(ref)
        for f_ in fields[0]:
            res, secs = run(fields=f_, refine=d["refine"])
            pa, c = per_sub(res)
            fld.add(name, f_, [_maxdiff(pa, pa_ref), _maxdiff(c, c_ref)], secs)
        for r_ in refines[0]:
            res, secs = run(fields=d["fields"], refine=r_)
            rfn.add(name, r_, [_maxdiff(per_sub(res)[1], c_ref)], secs)

        def display_max(res):
            gd_ok = res["chief_ok"][:, 0]
            pa = np.max(np.where(res["pa_ok"], res["pa"], -np.inf), axis=1)
            return np.max(res["gd"][gd_ok]), np.max(pa[np.isfinite(pa)])

        rows = {}
        for s_ in strides:
            res, secs = run(stride_=s_, lens=None)
            rows[s_] = (display_max(res), secs, len(res["subs"]))
        gd_ref, pa_ref = rows[(1, 1)][0]
        for s_, ((gd, pa), secs, count) in rows.items():
            strd.add(name, s_, [abs(gd - gd_ref), abs(pa - pa_ref)], secs, label=f"{s_[0]},{s_[1]} ({count})")
    lens_txt = ("5 × 3 lenslets of each, its centre and a corner lenslet" if quick
                else f"every {stride[0]}th lenslet in x and y")
    rfn.notes.append("Each level traces the 8 neighbours of the worst field found so far at half the previous "
                     "step (the first at half the grid spacing) and moves to the worst; `lfsim analyze` reports "
                     "the worst contrast found as `contrast_nyquist` of each sub-system and in the minima.")
    for kn in (pupil, grid, fld, rfn):
        kn.notes.append(f"Designs: {', '.join(names)} at their 1 D state, {lens_txt}; the error is the largest "
                        "over sub-systems and fields (and orientations, frequencies).")
    strd.notes.append(f"Designs: {', '.join(names)}{' (5 × 3 lenslets)' if quick else ''} at their 1 D state; "
                      "the label gives the sub-systems evaluated. "
                      "GD is the chief ray of each EI centre, so only the lenslet stride samples it.")
    return [pupil, grid, fld, rfn, strd]


# ===================================================================== render
def _reduced(path: Path, m: int, n: int):
    """The design at ``path`` with its lenslet array cut to m × n (same lenslet, smaller display)."""
    import tomllib

    import lfsim

    data = tomllib.loads(path.read_text())
    data["arrays"][data["ini"]["mla"]].update(m=m, n=n)
    return lfsim.Design.from_dict(data, str(path))


def measure_render(scenes: Path, quick: bool, log) -> list[Knob]:
    import lfsim
    from lfsim.content import load_content
    from lfsim.render.accuracy import error_vs_time
    from lfsim.render.focal_stack import FocalStackSpec

    spp_default = FocalStackSpec.__dataclass_fields__["spp"].default
    tess_default = FocalStackSpec.__dataclass_fields__["tessellation"].default
    content = load_content(scenes / "fig9_wall.toml")
    if quick:
        names, res = ["ini_ideal"], (24, 14)
        kw = dict(spps=(4, 16, spp_default), reference_spp=256, densities=(0.25, tess_default), pair_spp=4)
    else:
        names, res = ["ini_ideal", "ini_coaxial", "ini_freeform"], (128, 74)
        kw = dict(spps=(4, 16, spp_default, 256), reference_spp=4096,
                  densities=(0.125, 0.25, 0.5, tess_default, 2.0), pair_spp=64)
    spp = Knob("spp", "render", "Samples per pixel (analytic path)", "spp", ["RMSE / mean"],
               f"a {kw['reference_spp']}-spp render of the same path (another seed)",
               f"Mitsuba render of {res[0]}×{res[1]} px", spp_default,
               f"`lfsim focal-stack --spp {spp_default}` (`FocalStackSpec.spp`, lfsim/render/focal_stack.py)", [])
    tess = Knob("tessellation", "render", "Mesh tessellation (mesh path)", "density (× default segments)",
                ["RMSE / mean"], f"the analytic path with the same eye rays ({kw['pair_spp']} spp)",
                f"mesh build, load and walk of {res[0]}×{res[1]} px × {kw['pair_spp']} spp", tess_default,
                "`lfsim focal-stack --tessellation 1` × `DEFAULT_SEGMENTS`, `DEFAULT_LENSLET_SEGMENTS`, "
                "`DEFAULT_PRISM_SEGMENTS` (lfsim/render/meshes.py)",
                [Target(0, 0.01, "1 %: the bound the project's tests hold the default tessellation to "
                        "(tests/test_render_accuracy.py)")])
    for name in names:
        design = _reduced(scenes / f"{name}.toml", 5, 3) if quick else lfsim.load(scenes / f"{name}.toml")
        log(f"  render: {name}")
        d = error_vs_time(design, content, cdp_mm=750.0, resolution=res, **kw)
        for r in d["spp"]:
            spp.add(name, r["spp"], [r["rel_rmse"]], r["seconds"])
        for r in d["tessellation"]:
            tess.add(name, r["density"], [r["rel_rmse"]], r["seconds"],
                     label=f"{r['density']:g} ({r['segments']}/{r['lenslet_segments']}/{r['prism_segments']})")
    # Wavelength nodes per primary of a spectral render, on the dispersive freeform design.
    k_default = FocalStackSpec.__dataclass_fields__["wavelength_samples"].default
    wres, wspp = ((24, 14), 16) if quick else (res, spp_default)
    wk = (dict(samples=(1, 2, k_default), reference_samples=2 * k_default) if quick
          else dict(samples=(1, 2, 4, 8), reference_samples=32))
    waves = Knob("wavelength_samples", "render", "Wavelength nodes per display primary (spectral render)",
                 "nodes per primary", ["RMSE / mean"],
                 f"{wk['reference_samples']} nodes per primary, the same seed (common random numbers)",
                 f"the three passes of a {wres[0]}×{wres[1]} px, {wspp}-spp display image with diffraction",
                 k_default, f"`lfsim focal-stack --wavelength-samples {k_default}` (`FocalStackSpec."
                 "wavelength_samples`, lfsim/render/focal_stack.py)",
                 [Target(0, 0.03, "3 %: a fifth of the Monte Carlo noise of one such render (0.16 RMSE / "
                         "mean, seed to seed), so the quadrature is not what a user sees")])
    wname = "ini_freeform"
    wdesign = _reduced(scenes / f"{wname}.toml", 5, 3) if quick else lfsim.load(scenes / f"{wname}.toml")
    log(f"  render: wavelength nodes on {wname}")
    from lfsim.render.accuracy import wavelength_error

    wd = wavelength_error(wdesign, content, cdp_mm=750.0, resolution=wres, spp=wspp, **wk)
    for r in wd["samples"]:
        waves.add(wname, r["samples"], [r["rel_rmse"]], r["seconds"])
    waves.notes.append(f"Scene: the Fig. 9 wall's elemental images on {'5 × 3 lenslets of ' if quick else ''}"
                       f"{wname}, CDP and focus 750 mm, ideal eye with a 3 mm pupil. Seed-to-seed noise of one "
                       f"render: {wd['noise']:.3f} RMSE / mean. The nodes cost nothing: a ray traces one "
                       "wavelength whatever their number.")
    # Sampler of the retinal cameras: stratification of film, pupil, wavelength and diffraction.
    from lfsim.render.accuracy import sampler_noise
    from lfsim.render.eye import sampler_type

    sres = (48, 29) if quick else (512, 309)
    samplers = ("independent", "lfsim_sobol") if quick else ("independent", "multijitter", "lfsim_sobol")
    sspps = (4, 16) if quick else (16, spp_default, 256)
    s_default = (sampler_type(spp_default), spp_default if not quick else 16)
    sampler = Knob("sampler", "render", "Sampler of the retinal cameras (stratification)", "sampler, spp",
                   ["RMSE / mean"], "the converged image: RMS of two seeds' difference / √2 (the estimators "
                   "are unbiased)", f"one {sres[0]}×{sres[1]} px image in colour (three passes), kernels "
                   "compiled before", s_default,
                   f"`sampler_type()` (lfsim/render/eye.py) at `lfsim focal-stack --spp {spp_default}`",
                   [Target(0, 0.02, "2 %: the goal for the default focal stack's images, to be reached in "
                           "≤ 60 s for the whole stack on 2 cores (`benchmarks/focal_stack_noise.py` "
                           "measures the stack)")])
    sname = "ini_ideal"
    sdesign = _reduced(scenes / f"{sname}.toml", 5, 3) if quick else lfsim.load(scenes / f"{sname}.toml")
    log(f"  render: samplers on {sname}")
    sd = sampler_noise(sdesign, content, samplers=samplers, spps=sspps, resolution=sres,
                       kinds=("display",) if quick else ("display", "natural"),
                       diffraction=(True,) if quick else (True, False))
    for r in sd["rows"]:
        if r["kind"] == "natural" and not r["diffraction"]:
            continue
        series = f"{r['kind']}, {'diffraction' if r['diffraction'] else 'geometric'}"
        sampler.add(series, (r["sampler"], r["spp"]), [r["rel_rmse"]], r["seconds"],
                    label=f"{r['sampler']}, {r['spp']}")
    sampler.extra["line_by_setting_part"] = 0
    sampler.notes.append(
        f"Scene: the default focal stack's middle image ({'5 × 3 lenslets of ' if quick else ''}{sname}, the "
        "Fig. 9 wall, CDP 750 mm, ideal eye with a 3 mm pupil focused at 1000 mm; colour with 4 wavelength "
        "nodes per primary). Samplers: Mitsuba's `independent` and `multijitter` (film, pupil and wavelength "
        "each stratified in their own 2D pattern, paired at random) and lfsim's `lfsim_sobol` "
        "(lfsim/render/sobol.py: Owen-scrambled Sobol points, stratified jointly over film, pupil, wavelength "
        "and the diffraction kick). \"geometric\": `--no-diffraction`. The diffraction kicks are drawn from "
        "the same sampler, so every sampler stratifies them as it stratifies the rest.")
    extent = "5 × 3 lenslets of each design" if quick else "each design"
    for kn in (spp, tess):
        kn.notes.append(f"Scene: the Fig. 9 wall's elemental images on {extent} ({', '.join(names)}), CDP and "
                        "focus 750 mm, ideal eye with a 3 mm pupil.")
    tess.notes.append("Labels: density (segments per lens semi-diameter / per lenslet pitch / per prism half-width).")
    return [spp, tess, waves, sampler, _ei_spp(scenes, quick, log)]


def _ei_spp(scenes: Path, quick: bool, log) -> Knob:
    """Samples per display pixel of path-traced elemental images (a Mitsuba-scene content)."""
    import lfsim
    from lfsim.content import load_content, shade_display
    from lfsim.ini.model import model_at_depth
    from lfsim.render.display import DisplayLayout
    from lfsim.render.focal_stack import FocalStackSpec

    default = FocalStackSpec.__dataclass_fields__["ei_spp"].default
    spps, ref_spp = ((4, default), 64) if quick else ((4, default, 64), 128)
    knob = Knob("ei_spp", "render", "Samples per display pixel (path-traced elemental images)", "spp",
                ["RMSE / mean", "reported noise"],
                f"a {ref_spp}-spp render (another seed), less the reference's own noise",
                "path tracing every display pixel's chief ray (kernels compiled before)", default,
                f"`lfsim focal-stack --ei-spp {default}` (`FocalStackSpec.ei_spp`, lfsim/render/focal_stack.py)", [])
    table = load_content(scenes / "tabletop.toml")
    name = "ini_ideal"
    design = _reduced(scenes / f"{name}.toml", 5, 3) if quick else lfsim.load(scenes / f"{name}.toml")
    log(f"  render: path-traced elemental images on {name}")
    model = model_at_depth(design, 1000.0 / table.view.cdp_mm)
    layout = DisplayLayout.from_model(model, 0)
    ref = shade_display(model, table, layout, spp=ref_spp, seed=101)
    has = ref.image.sum(axis=-1) > 0
    for n in spps:
        r, secs = _best_time(lambda n=n: shade_display(model, table, layout, spp=n, seed=1), 1)
        e2 = np.mean((r.image - ref.image)[has] ** 2) / ref.image[has].mean() ** 2
        knob.add(name, n, [math.sqrt(max(e2 - ref.noise_rel ** 2, 0.0)), r.noise_rel], secs)
    knob.notes.append(
        f"Scene: the tabletop (scenes/tabletop.toml, a lit Mitsuba scene) on {'5 × 3 lenslets of ' if quick else ''}"
        f"{name} ({layout.width} × {layout.height} display pixels), CDP {table.view.cdp_mm:g} mm. The errors are "
        "per display pixel; a retinal pixel averages many display pixels, so the retinal images are far less "
        "noisy. \"reported noise\": the standard error the render itself reports (two independent halves of "
        "its samples); it tracks the measured error. No target: the display's noise is an input of the retinal "
        "images' own spp knob.")
    return knob


# ======================================================================== eye
def measure_eye(quick: bool, log) -> list[Knob]:
    from lfsim.render.eye_models import axial_rms_spot, solve_accommodation

    solve = solve_accommodation.__wrapped__  # uncached: every call is timed
    par = inspect.signature(solve).parameters
    default = ("rms", par["xatol"].default, par["n_rings"].default)
    pupil = 3.0
    dists = [750.0] if quick else [600.0, 1000.0, 1400.0]
    ref_rings, ref_tol = (24, 1e-7) if quick else (96, 1e-9)
    settings = [("paraxial", None, None)] + [("rms", t, default[2]) for t in
                                             ([1e-2, default[1]] if quick else [1e-2, 1e-3, 1e-4, default[1], 1e-7])]
    settings += [] if quick else [("rms", default[1], r) for r in (4, 8, 12, 48)]
    knob = Knob("accommodation", "eye", "Arizona-eye accommodation solve", "criterion, xatol (D), rings",
                ["accommodation error (D)", "excess RMS spot (µm)"],
                f"criterion rms with xatol {ref_tol:g} D and {ref_rings} rings",
                f"one uncached solve per distance, summed over {len(dists)} distance(s)", default,
                "`solve_accommodation(criterion=\"rms\", xatol=1e-5, n_rings=24)` (lfsim/render/eye_models.py)",
                [Target(0, 0.01, "0.01 D: the last digit of the focus-cue offsets lfsim reports "
                        "(docs/rendering.md)")])
    log(f"  eye: {len(dists)} distance(s), {pupil:g} mm pupil")
    refs = {dd: solve(dd, pupil, 550.0, "rms", ref_tol, ref_rings) for dd in dists}
    ref_rms = {dd: axial_rms_spot(refs[dd], dd, pupil, 550.0, ref_rings) for dd in dists}
    for crit, tol, rings in settings:
        t0 = time.perf_counter()
        if crit == "paraxial":
            got = {dd: solve(dd, pupil, 550.0, "paraxial") for dd in dists}
        else:
            got = {dd: solve(dd, pupil, 550.0, "rms", tol, rings) for dd in dists}
        secs = time.perf_counter() - t0
        err = max(abs(got[dd] - refs[dd]) for dd in dists)
        excess = max(axial_rms_spot(got[dd], dd, pupil, 550.0, ref_rings) - ref_rms[dd] for dd in dists)
        label = "paraxial" if crit == "paraxial" else f"rms, {tol:g}, {rings}"
        knob.add("Arizona eye", (crit, tol, rings), [err, max(excess, 0.0) * 1000.0], secs, label=label)
    knob.notes.append(f"Focus distances {', '.join(f'{dd:g}' for dd in dists)} mm, {pupil:g} mm pupil, 550 nm; the "
                      "excess RMS spot is the on-axis retinal spot at the solved accommodation minus that at the "
                      "reference.")
    return [knob]


# ==================================================================== verdict
def _targeted(knob: Knob, r: dict) -> list:
    """The row's errors that have a target (all errors when the knob has none)."""
    return [r["errors"][t.index] for t in knob.targets] if knob.targets else list(r["errors"])


def _meets(knob: Knob, r: dict) -> bool:
    return all(r["errors"][t.index] is not None and r["errors"][t.index] <= t.value for t in knob.targets)


def verdict(knob: Knob) -> dict:
    """Errors and times at the default (worst series), and the cheapest setting meeting every target per series."""
    out = {"default": _label(knob.default), "error_at_default": None, "seconds_at_default": [],
           "meets_target": None, "cheapest": {}}
    drows = knob.default_rows()
    if drows:
        cols = list(zip(*[_targeted(knob, r) for r in drows]))
        out["error_at_default"] = [None if any(e is None for e in c) else max(c) for c in cols]
        out["seconds_at_default"] = [r["seconds"] for r in drows]
    if not knob.targets:
        return out
    ok_default = True
    for s in knob.series():
        rows = [r for r in knob.rows if r["series"] == s]
        meets = [r for r in rows if _meets(knob, r)]
        out["cheapest"][s] = min(meets, key=lambda r: r["seconds"])["label"] if meets else None
        ok_default &= any(_meets(knob, r) for r in rows if r["setting"] == knob.default)
    out["meets_target"] = bool(ok_default) if drows else None
    return out


def _errs(knob: Knob, r: dict) -> str:
    return " / ".join(_fmt(e) for e in _targeted(knob, r))


def why(knob: Knob) -> str:
    """The default and why, from the measured figures."""
    v = verdict(knob)
    parts = []
    for s in knob.series():
        rows = [r for r in knob.rows if r["series"] == s]
        dflt = [r for r in rows if r["setting"] == knob.default]
        if not dflt:
            continue
        dr = dflt[0]
        text = f"{s}: error {_errs(knob, dr)} in {dr['seconds']:.3g} s at the default"
        if knob.targets:
            cheap = [r for r in rows if _meets(knob, r)]
            if _meets(knob, dr):
                best = min(cheap, key=lambda r: r["seconds"])
                if best is dr:
                    text += ", the cheapest setting measured that meets the target"
                else:
                    text += (f", within the target; {best['label']} meets it in {best['seconds']:.3g} s "
                             f"({best['seconds'] / dr['seconds']:.2g}× the default's time, error {_errs(knob, best)})")
            elif cheap:
                best = min(cheap, key=lambda r: r["seconds"])
                text += (f", OUTSIDE the target; {best['label']} meets it in {best['seconds']:.3g} s "
                         f"(error {_errs(knob, best)})")
            else:
                text += ", OUTSIDE the target, and so is every setting measured"
        else:
            cheaper = [r for r in rows if r["seconds"] < dr["seconds"]]
            dearer = [r for r in rows if r["seconds"] > dr["seconds"]]
            if cheaper:
                c = max(cheaper, key=lambda r: r["seconds"])
                text += f" ({c['label']}: {_fmt(c['errors'][0])} in {c['seconds']:.3g} s"
                if dearer:
                    e = min(dearer, key=lambda r: r["seconds"])
                    text += f"; {e['label']}: {_fmt(e['errors'][0])} in {e['seconds']:.3g} s)"
                else:
                    text += ")"
        if knob.key == "tracer_precision":
            for r in rows:
                if r["setting"] == "float32" and r["errors"][0] is not None:
                    text += (f"; float32 (the render path's precision): error {_fmt(r['errors'][0])} mm, "
                             f"{dr['seconds'] / r['seconds']:.2g}× the float64 speed")
                    pp = knob.extra.get("pixel_pitch", {}).get(s)
                    if pp:
                        text += f", 1/{pp / r['errors'][0]:.0f} of its {pp * 1000:g} µm display pixel"
        parts.append(text)
    slope = _spp_slope(knob) if knob.key == "spp" else None
    lead = f"Default {v['default']} ({knob.default_source}). "
    if knob.targets:
        lead += "Target: " + "; ".join(f"{knob.errors[t.index]} {_bound(t)} ({t.why})"
                                       for t in knob.targets) + ". "
    if slope is not None:
        lead += f"Measured: the error falls as spp^{slope:.2f} (least squares over all designs). "
    return lead + "; ".join(parts) + "."


def _spp_slope(knob: Knob) -> float | None:
    x = [math.log(r["setting"]) for r in knob.rows if r["errors"][0]]
    y = [math.log(r["errors"][0]) for r in knob.rows if r["errors"][0]]
    if len(set(x)) < 2:
        return None
    X = np.column_stack([x, np.ones(len(x))])
    series = [r["series"] for r in knob.rows if r["errors"][0]]
    for s in dict.fromkeys(series):  # one intercept per design, a common slope
        X = np.column_stack([X, [1.0 if t == s else 0.0 for t in series]])
    coef, *_ = np.linalg.lstsq(X[:, [0] + list(range(2, X.shape[1]))], np.array(y), rcond=None)
    return float(coef[0])


# ===================================================================== output
def plot_knob(knob: Knob, path: Path) -> None:
    """Error against seconds, one panel per error column, one line per series; the default starred."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import NullFormatter

    from lfsim.fileio import save_figure

    ne = len(knob.errors)
    fig, axes = plt.subplots(1, ne, figsize=(5.2 * ne, 3.9), squeeze=False)
    positive = [e for r in knob.rows for e in r["errors"] if e]
    floor = min(positive) / 10.0 if positive else 1e-16
    for j, ax in enumerate(axes[0]):
        part = knob.extra.get("line_by_setting_part")
        lines = [(s, None) for s in knob.series()] if part is None else list(dict.fromkeys(
            (r["series"], r["setting"][part]) for r in knob.rows))
        for s, sub in lines:
            rows = [r for r in knob.rows if r["series"] == s and r["errors"][j] is not None
                    and (sub is None or r["setting"][part] == sub)]
            if not rows:
                continue
            xs = [r["seconds"] for r in rows]
            ys = [max(r["errors"][j], floor) for r in rows]
            line, = ax.loglog(xs, ys, "o-", label=s if sub is None else f"{s}: {sub}", ms=4)
            for r, x, y in zip(rows, xs, ys):
                ax.annotate(r["label"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
                if r["setting"] == knob.default:
                    ax.plot([x], [y], "*", ms=14, color=line.get_color(), mec="k", zorder=5)
        for t in knob.targets:
            if t.index == j and t.value > 0:
                ax.axhline(t.value, ls="--", color="0.4", lw=1, label="target")
        ax.xaxis.set_minor_formatter(NullFormatter())  # decade labels only: minor ones overlap
        ax.set_xlabel("seconds")
        ax.set_ylabel(knob.errors[j])
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    # Points are joined in the order of the setting swept (a run time need not grow with it).
    fig.suptitle(textwrap.fill(f"{knob.title}: error against run time, points joined in setting order "
                               f"(★ default; zero errors drawn at {floor:.0e})", 60 * ne), fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=100)
    plt.close(fig)


def _cell(text) -> str:
    """A markdown table cell: pipes in the text (|Δx|) escaped."""
    return str(text).replace("|", "\\|")


def _bound(t: Target) -> str:
    return "= 0" if t.value == 0 else f"≤ {_fmt(t.value)}"


def _table(knob: Knob) -> list[str]:
    head = [_cell(h) for h in ("design", knob.setting, *knob.errors, "seconds", "")]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * 2 + "---:|" * (len(knob.errors) + 1) + "---|"]
    for r in knob.rows:
        mark = "**default**" if r["setting"] == knob.default else ""
        lines.append("| " + " | ".join([r["series"], r["label"], *(_fmt(e) for e in r["errors"]),
                                        f"{r['seconds']:.3g}", mark]) + " |")
    return lines


def markdown(doc: dict, knobs: list[Knob]) -> str:
    m = doc["machine"]
    out = ["# Accuracy: error against run time", "",
           f"Generated by `python benchmarks/accuracy_report.py{' --quick' if doc['quick'] else ''}` "
           f"({doc['generated']}; {doc['total_seconds']:.0f} s) on {m['cpus']} CPU cores, Python {m['python']}, "
           f"Dr.Jit {m['drjit']}, Mitsuba {m['mitsuba']}, {m['platform']}. Re-run it after a change to regenerate "
           "this page and its plots; run times are this machine's and vary by tens of percent between runs.", "",
           "Every approximation lfsim makes has a knob. For each one, every setting's error is measured against a "
           "converged reference (a setting far beyond the default, or an exact answer) together with its run "
           "time; the default is read from the code that sets it and is checked against an accuracy target. "
           "Plots: error against seconds, the default starred, the target dashed. \"Cheapest\" is the fastest "
           "setting measured; time differences below about 20 % are within this machine's run-to-run noise.", "",
           "## Summary", "",
           "| stage | knob | lfsim default | errors at the default (targeted ones, worst design) "
           "| seconds at the default | target | meets it | cheapest setting that meets it |",
           "|---|---|---|---:|---:|---|---|---|"]
    for k, v in zip(knobs, doc["verdicts"]):
        t = _cell("; ".join(f"{k.errors[g.index]} {_bound(g)}" for g in k.targets) or "—")
        err = " / ".join(_fmt(e) for e in v["error_at_default"]) if v["error_at_default"] else "—"
        meets = {True: "yes", False: "**no**", None: "—"}[v["meets_target"]]
        cheap = "—" if not v["cheapest"] else "; ".join(f"{s}: {c or 'none'}" for s, c in v["cheapest"].items())
        secs = ", ".join(f"{s:.3g}" for s in v["seconds_at_default"]) or "—"
        out.append(f"| {k.stage} | [{k.title}](#{k.key}) | {v['default']} | {err} | {secs} "
                   f"| {t} | {meets} | {cheap} |")
    stage_titles = {"tracer": "Tracer", "metrics": "Metrics sampling", "render": "Rendering", "eye": "Eye model"}
    stage = None
    for k in knobs:
        if k.stage != stage:
            stage = k.stage
            out += ["", f"## {stage_titles[stage]}"]
        out += ["", f'<a id="{k.key}"></a>', "", f"### {k.title}", "",
                f"Error against: {k.reference}. Time: {k.timing}.", ""]
        out += [" ".join(k.notes), ""] if k.notes else []
        out += _table(k)
        out += ["", f"![{k.title}: error against run time](img/accuracy_{k.key}.png)", "",
                f"**Default and why.** {why(k)}"]
    out += ["", "## Stiff and extreme cases", "",
            "The stiff and extreme cases (telecentric viewing window, CDP at 0 D, g = f_MLA, grazing incidence, "
            "TIR at the critical angle ± 1e-9 rad, XY coefficients from 1e-2 to 1e-20, lenslets hit at 0.999 of "
            "their aperture, hemispherical lenslets, 1 µm pixels over 1 m, 101 × 101 arrays, zero thickness, the "
            "tunable lens at the ends of its range) are tests, each in float64 and float32: "
            "`.venv/bin/python -m pytest tests/test_stiff.py tests/test_extreme.py` prints the accuracy each one "
            "measured (section \"measured accuracy of stiff and extreme cases\").", ""]
    return "\n".join(out)


def _machine() -> dict:
    import drjit
    import mitsuba

    return {"cpus": os.cpu_count(), "python": platform.python_version(), "drjit": drjit.__version__,
            "mitsuba": mitsuba.__version__, "platform": f"{platform.system()} {platform.machine()}"}


def report(out_dir="docs", quick: bool = False, log=lambda msg: None, scenes: Path | None = None,
           stages=("tracer", "metrics", "render", "eye")) -> dict:
    """Measure every knob and write ``out_dir/accuracy.md`` and ``out_dir/img/accuracy_<knob>.png``.

    ``quick``: a small version (fewer settings, rays, sub-systems and pixels; one
    design per stage) for tests. Returns the document (knobs with their rows,
    verdicts, machine, timings), JSON-ready.
    """
    from datetime import datetime

    from lfsim.fileio import write_text

    scenes = Path(scenes) if scenes is not None else SCENES
    if not (scenes / "fig9_wall.toml").is_file():
        raise ValueError(f"{scenes}: scenes folder not found: the report measures lfsim's shipped designs")
    t0 = time.perf_counter()
    knobs: list[Knob] = []
    for stage in stages:
        log(f"{stage} ...")
        if stage == "tracer":
            knobs += measure_tracer(scenes, quick, log)
        elif stage == "metrics":
            knobs += measure_metrics(scenes, quick, log)
        elif stage == "render":
            knobs += measure_render(scenes, quick, log)
        elif stage == "eye":
            knobs += measure_eye(quick, log)
        else:
            raise ValueError(f"stage = {stage!r}: expected tracer, metrics, render or eye")
    out = Path(out_dir)
    doc = {"generated": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"), "quick": bool(quick),
           "machine": _machine(), "knobs": [_knob_dict(k) for k in knobs], "verdicts": [verdict(k) for k in knobs],
           "why": {k.key: why(k) for k in knobs}, "plots": [f"img/accuracy_{k.key}.png" for k in knobs]}
    for k in knobs:
        plot_knob(k, out / "img" / f"accuracy_{k.key}.png")
    doc["total_seconds"] = round(time.perf_counter() - t0, 1)
    write_text(out / "accuracy.md", markdown(doc, knobs) + "\n")
    doc["markdown"] = "accuracy.md"
    return doc


def _knob_dict(k: Knob) -> dict:
    d = asdict(k)
    d["default"] = _label(k.default)
    for r in d["rows"]:
        r["setting"] = _label(r["setting"])
    return d


def main(argv=None) -> int:
    import argparse
    import json

    from lfsim.fileio import check_writable, write_json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="a small version (fewer settings, rays and pixels)")
    ap.add_argument("--out", default=str(ROOT / "docs"), help="where accuracy.md and img/ go (default docs/)")
    ap.add_argument("--json", action="store_true", help="print the document as JSON instead of the summary")
    args = ap.parse_args(argv)
    result = ROOT / "benchmarks" / "results" / ("accuracy_report_quick.json" if args.quick else "accuracy_report.json")
    try:
        check_writable(args.out, "--out", folder=True)
        check_writable(result, "results")
    except ValueError as e:
        print(f"accuracy_report: error: {e}", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    doc = report(args.out, quick=args.quick, log=lambda msg: print(f"{time.perf_counter() - t0:7.1f} s  {msg}",
                                                                   file=sys.stderr, flush=True))
    write_json(result, doc)
    if args.json:
        print(json.dumps(doc, indent=2))
        return 0
    for k, v in zip(doc["knobs"], doc["verdicts"]):
        meets = {True: "meets its target", False: "MISSES its target", None: "no target"}[v["meets_target"]]
        err = " / ".join("-" if e is None else f"{e:.3g}" for e in v["error_at_default"] or [None])
        secs = ", ".join(f"{s:.3g}" for s in v["seconds_at_default"])
        print(f"{k['stage']:8s} {k['key']:17s} default {v['default']:>14s}  error {err:>9s}  seconds {secs:>24s}  "
              f"{meets}")
    print(f"wrote {Path(args.out) / 'accuracy.md'}, {len(doc['plots'])} plots and {result} "
          f"in {doc['total_seconds']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
