"""``lfsim regress``: re-render a design's focal stack and re-compute its metrics against a baseline.

:func:`update` renders the focal stack (:func:`lfsim.render.focal_stack.focal_stack`)
with two seeds, computes the design metrics (:func:`lfsim.analysis.ini_analysis.analyze`)
and stores both with the options and tolerances in a baseline folder
(:mod:`.baseline`). :func:`check` renders the candidate the same way (same
options, by default the same seeds: common random numbers) and compares:

* each retinal image (display and natural view per focus distance): change,
  detail (blur) and, for the display, error against the natural view, with
  the noise-aware statistics of :mod:`.noise`;
* the render's field of view and tunable-lens power, and the design metrics
  (GD, PA, contrast at Nyquist, RMS spot, first-order data per CDP depth),
  which are deterministic, against tight relative tolerances.

Options not given for a check come from the baseline; given ones replace
them for the candidate (``focus_mm``: an eye focused elsewhere, ``set``: a
changed design, ``seed``: other Monte Carlo seeds), except the spp and the
image size, which must match the baseline's.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import baseline as bl
from . import noise
from .checks import Check, numeric_check, table

DEFAULT_CONTENT = "scenes/fig9_wall.toml"
DEFAULT_SPP = 32
KINDS = ("display", "natural")

#: Render and metric options (stored in the baseline); None: the content's [view] or the design's default.
DEFAULT_OPTIONS = {
    "content": DEFAULT_CONTENT, "focus_mm": None, "cdp_mm": None, "pupil_mm": None, "spp": DEFAULT_SPP,
    "resolution": None, "seed": 0, "eye": "ideal", "mla_cells": "per_surface", "optics": "analytic",
    "tessellation": 1.0, "set": [], "metrics": True, "stride": None, "depths": None,
}
CHOICES = {"eye": ("ideal", "arizona"), "mla_cells": ("per_surface", "fixed"), "optics": ("analytic", "mesh")}

#: Design metrics compared, with the better direction ("lower", "higher" or "either").
SUMMARY_METRICS = {
    "gd_max_deg": "lower", "gd_mean_deg": "lower", "pa_max": "lower", "pa_mean": "lower",
    "pa_within_target": "higher", "gd_within_target": "higher", "gd_failed": "lower",
    "pa_fields_failed": "lower", "rays_failed": "lower", "nyquist_cpd": "either",
    "contrast_nyquist_min": "higher", "contrast_nyquist_mean": "higher", "rms_spot_mean_arcmin": "lower",
    "local_distortion_pct_max": "lower", "subsystems_evaluated": "either",
}
DEPTH_METRICS = {
    "contrast_nyquist_min": "higher", "contrast_nyquist_mean": "higher", "rms_spot_mean_arcmin": "lower",
    "rms_spot_max_arcmin": "lower", "gd_max_deg": "lower", "pa_max": "lower",
}
FIRST_ORDER = ("tunable_power_diopters", "fov_deg", "pixel_arcmin", "d_v", "D_v", "nyquist_cpd")


class RegressionInputError(ValueError):
    """A bad option for a regression run (one line naming the option and value)."""


# ------------------------------------------------------------------ options
def _flag(key: str) -> str:
    return "--" + key.replace("_", "-")


def _float(v, key, positive=True, allow_inf=False) -> float:
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise RegressionInputError(f"{_flag(key)} = {v!r}: expected a number") from None
    if math.isnan(x) or (math.isinf(x) and not allow_inf) or (positive and not x > 0):
        raise RegressionInputError(f"{_flag(key)} = {v!r}: expected a {'positive ' if positive else ''}"
                                   f"{'number (inf allowed)' if allow_inf else 'finite number'}")
    return x


def normalize_options(opts: dict) -> dict:
    """Validated, JSON-ready options (unknown keys and bad values are :class:`RegressionInputError`)."""
    unknown = sorted(set(opts) - set(DEFAULT_OPTIONS))
    if unknown:
        raise RegressionInputError(f"option {unknown[0]!r}: unknown (allowed: {', '.join(DEFAULT_OPTIONS)})")
    o = dict(DEFAULT_OPTIONS)
    o.update({k: v for k, v in opts.items()})
    out = {"content": str(o["content"])}
    out["focus_mm"] = None if o["focus_mm"] is None else [_float(f, "focus_mm") for f in o["focus_mm"]]
    if out["focus_mm"] is not None and not out["focus_mm"]:
        raise RegressionInputError("--focus-mm = []: give at least one distance")
    cdp = None if o["cdp_mm"] is None else _float(o["cdp_mm"], "cdp_mm", allow_inf=True)
    out["cdp_mm"] = "inf" if cdp is not None and math.isinf(cdp) else cdp
    out["pupil_mm"] = None if o["pupil_mm"] is None else _float(o["pupil_mm"], "pupil_mm")
    spp = o["spp"]
    if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
        raise RegressionInputError(f"--spp = {spp!r}: must be an integer >= 1")
    out["spp"] = int(spp)
    res = o["resolution"]
    if res is not None:
        try:
            w, h = (int(v) for v in res)
        except (TypeError, ValueError):
            raise RegressionInputError(f"--resolution = {res!r}: expected two integers W,H") from None
        if w < 8 or h < 8:
            raise RegressionInputError(f"--resolution = {w},{h}: at least 8x8 px (the noise test uses tiles)")
        res = [w, h]
    out["resolution"] = res
    seed = o["seed"]
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise RegressionInputError(f"--seed = {seed!r}: must be an integer >= 0")
    out["seed"] = int(seed)
    for key, allowed in CHOICES.items():
        if o[key] not in allowed:
            raise RegressionInputError(f"{_flag(key)} = {o[key]!r}: allowed: {', '.join(allowed)}")
        out[key] = o[key]
    out["tessellation"] = _float(o["tessellation"], "tessellation")
    sets = o["set"] or []
    if isinstance(sets, dict):
        sets = [f"{k}={v!r}" for k, v in sets.items()]
    from ..design.overrides import parse_sets

    parse_sets(sets)  # validates KEY=VALUE syntax
    out["set"] = [str(s) for s in sets]
    out["metrics"] = bool(o["metrics"])
    st = o["stride"]
    if st is not None:
        try:
            a, b = (int(v) for v in st)
        except (TypeError, ValueError):
            raise RegressionInputError(f"--stride = {st!r}: expected two integers SX,SY") from None
        if a < 1 or b < 1:
            raise RegressionInputError(f"--stride = {st!r}: strides must be >= 1")
        st = [a, b]
    out["stride"] = st
    out["depths"] = None if o["depths"] is None else [_float(d, "depths", positive=False) for d in o["depths"]]
    return out


def _cdp(v) -> float | None:
    return None if v is None else float(v)


# ------------------------------------------------------------------ rendering and metrics
@dataclass
class Rendered:
    """Retinal images per seed, ``{(kind, focus index): [image per seed]}``, and the render's setup."""

    images: dict
    options: dict  # resolved: focus_mm, cdp_mm, pupil_mm and resolution filled in
    info: dict  # fov_deg, tunable_power_diopters, resolution
    seconds: float
    focal_stacks: list = field(default_factory=list)  # index.json documents, one per seed


def load_design(path, opts: dict):
    from ..design.overrides import load_with_overrides, parse_sets

    design = load_with_overrides(path, parse_sets(opts["set"]))
    if design.ini is None:
        raise RegressionInputError(f"{path}: ini = missing: lfsim regress needs an InI design ([ini] section)")
    return design


def render(design, opts: dict, seeds, log=None) -> Rendered:
    """Render the focal stack once per seed (into a temporary folder); keep the retinal images."""
    from ..content import load_content
    from ..render.focal_stack import FocalStackSpec, focal_stack

    content = load_content(opts["content"])
    view = content.view
    focus = opts["focus_mm"] or list(view.focus_mm)
    cdp = _cdp(opts["cdp_mm"]) if opts["cdp_mm"] is not None else view.cdp_mm
    pupil = opts["pupil_mm"] if opts["pupil_mm"] is not None else view.pupil_diameter_mm
    res = tuple(opts["resolution"]) if opts["resolution"] else None
    images: dict = {}
    docs = []
    t0 = time.perf_counter()
    for seed in seeds:
        spec = FocalStackSpec(focus_mm=list(focus), cdp_mm=cdp, pupil_diameter_mm=pupil, spp=opts["spp"],
                              resolution=res, seed=int(seed), eye_model=opts["eye"], mla_cells=opts["mla_cells"],
                              optics=opts["optics"], tessellation=opts["tessellation"], focus_cues=False)
        with tempfile.TemporaryDirectory(prefix="lfsim-regress-") as tmp:
            doc, stack = focal_stack(design, content, tmp, spec, log=log or (lambda m: None))
        docs.append(doc)
        for i, f in enumerate(focus):
            for kind in KINDS:
                images.setdefault((kind, i), []).append(np.asarray(stack["images"][(kind, f)], np.float32))
        if log:
            log(f"seed {seed}: {len(focus)} focus distance(s) in {doc['total_s']:.1f} s")
    d0 = docs[0]
    resolved = dict(opts, focus_mm=[float(f) for f in focus], cdp_mm="inf" if math.isinf(cdp) else cdp,
                    pupil_mm=float(pupil), resolution=[int(v) for v in d0["resolution"]])
    info = {"fov_deg": [float(v) for v in d0["fov_deg"]], "tunable_power_diopters": d0["tunable_power_diopters"],
            "resolution": resolved["resolution"]}
    return Rendered(images, resolved, info, time.perf_counter() - t0, docs)


def design_metrics(design, opts: dict) -> dict:
    """Flat ``{name: {"value", "direction"}}`` of the design metrics (``lfsim analyze``)."""
    from ..analysis.ini_analysis import analyze

    doc = analyze(design, None, stride=tuple(opts["stride"]) if opts["stride"] else None,
                  depths_diopters=opts["depths"], plots=False)
    out = {}
    s = doc["summary"]
    for k, d in SUMMARY_METRICS.items():
        if k in s:
            out[f"summary.{k}"] = {"value": s[k], "direction": d}
    for D, b in doc["by_depth"].items():
        for k, d in DEPTH_METRICS.items():
            if k in b:
                out[f"by_depth[{D}].{k}"] = {"value": b[k], "direction": d}
        fo = b.get("first_order") or {}
        for k in FIRST_ORDER:
            v = fo.get(k)
            if isinstance(v, (list, tuple)):
                for j, x in enumerate(v):
                    out[f"by_depth[{D}].first_order.{k}[{j}]"] = {"value": x, "direction": "either"}
            elif v is not None:
                out[f"by_depth[{D}].first_order.{k}"] = {"value": v, "direction": "either"}
    return {k: {"value": None if v["value"] is None or not math.isfinite(float(v["value"])) else float(v["value"]),
                "direction": v["direction"]} for k, v in out.items()}


def _sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


# ------------------------------------------------------------------ update
def update(design_path, baseline_dir, given: dict | None = None, log=None) -> dict:
    """Create (or re-create) the baseline of ``design_path`` in ``baseline_dir``.

    ``given``: options (see ``DEFAULT_OPTIONS``); omitted ones come from the
    existing baseline, if any, else the defaults. Tolerances of an existing
    baseline are kept. Returns the ``baseline.json`` document.
    """
    from .. import __version__
    from ..design.writer import design_text

    folder = Path(baseline_dir)
    given = {k: v for k, v in (given or {}).items() if v is not None}
    bl.check_replaceable(folder)
    old = None
    if (folder / "baseline.json").is_file():
        try:
            old = bl.read(folder)
        except bl.BaselineError:
            old = None
    base_opts = dict(DEFAULT_OPTIONS)
    if old is not None:
        base_opts.update(_options_from_baseline(old, folder))
        for k in ("focus_mm", "cdp_mm", "pupil_mm", "resolution"):  # resolved values: re-resolve unless given
            base_opts[k] = old["options"].get("given", {}).get(k)
    opts = normalize_options(dict(base_opts, **(given or {})))
    design = load_design(design_path, opts)
    seeds = [opts["seed"], opts["seed"] + 1]
    r = render(design, opts, seeds, log)
    metrics = design_metrics(design, opts) if opts["metrics"] else {}
    tol = dict(bl.DEFAULT_TOLERANCES)
    if old is not None:
        tol.update(old["tolerances"])
    noise_doc = {}
    for (kind, i), (b1, b2) in sorted(r.images.items()):
        noise_doc[f"{kind} {r.options['focus_mm'][i]:g} mm"] = _noise_summary(b1, b2, tol)
    stored = dict(r.options, content=bl.relative(r.options["content"], folder),
                  given=_given_keys(old, given, r.options))
    doc = {
        "format": bl.FORMAT, "version": bl.VERSION, "created": _now(), "lfsim_version": __version__,
        "design": {"path": bl.relative(design_path, folder), "sha256": _sha256(design_path),
                   "name": design.name, "copy": "design.toml"},
        "options": stored, "seeds": seeds, "tolerances": tol, "render": r.info,
        "render_s": round(r.seconds, 3), "noise": noise_doc, "metrics": metrics,
    }
    header = [f"{design.name}: the design of this regression baseline, as rendered",
              f"(from {design_path}" + (f" with --set {' '.join(opts['set'])})" if opts["set"] else ")")]
    bl.write(folder, doc, r.images, design_text(design.raw, header) if getattr(design, "raw", None) else None)
    if log:
        log(f"baseline {folder}: {len(r.images)} images x {len(seeds)} seeds, {len(metrics)} metrics")
    return bl.read(folder)


def _given_keys(old, given, resolved) -> dict:
    """The options fixed by the user (not resolved from the content), kept for a later --update."""
    prev = (old or {}).get("options", {}).get("given", {}) if old else {}
    out = dict(prev)
    for k in ("focus_mm", "cdp_mm", "pupil_mm", "resolution"):
        if given and given.get(k) is not None:
            out[k] = resolved[k]
    return out


def _noise_summary(b1, b2, tol) -> dict:
    """Seed-to-seed noise of one image and the smallest RMS change a reseeded candidate would show.

    With independent seeds ``x = (C1 - B1)(C2 - B2)`` has variance about
    ``Var(C1 - B1) Var(C2 - B2)``, estimated per pixel by ``d⁴ / 3`` with
    ``d = B1 - B2`` (Gaussian fourth moment), so the threshold of
    :func:`noise.change` is predicted from the baseline alone.
    """
    b1, b2 = np.asarray(b1, np.float64), np.asarray(b2, np.float64)
    d2 = (b1 - b2) ** 2
    mean = max(float(np.mean(0.5 * (b1 + b2))), 1e-12)
    t = noise.tile_sums(d2 * d2 / 3.0, tol["tile_px"])
    thr = math.sqrt(tol["z_max"] * math.sqrt(float(np.sum(t))) / b1.size) / mean
    return {"rms_noise": math.sqrt(float(np.mean(d2)) / 2.0) / mean, "mean": mean,
            "reseed_change_threshold": max(thr, tol["image_change_floor"])}


def _options_from_baseline(doc: dict, folder: Path) -> dict:
    o = {k: v for k, v in doc["options"].items() if k in DEFAULT_OPTIONS}
    o["content"] = str(bl.resolve(o["content"], folder))
    return o


# ------------------------------------------------------------------ check
@dataclass
class RegressionResult:
    """The checks of a run, the report document and the paths written."""

    checks: list[Check]
    doc: dict
    files: dict = field(default_factory=dict)

    @property
    def failed(self) -> bool:
        return any(c.failed for c in self.checks)

    def failing(self) -> list[Check]:
        return [c for c in self.checks if c.failed]

    def table(self, include_ok: bool = False) -> str:
        return table(self.checks, include_ok=include_ok)

    def summary(self) -> str:
        n = len(self.checks)
        counts = {s: sum(c.status == s for c in self.checks) for s in ("worse", "changed", "better", "ok")}
        head = "FAILED" if self.failed else "passed"
        return (f"{head}: {n} checks: {counts['worse']} worse, {counts['changed']} changed, "
                f"{counts['better']} better, {counts['ok']} ok")


def check(design_path, baseline_dir, given: dict | None = None, out_dir=None, junit=None, log=None,
          heatmaps: bool = True) -> RegressionResult:
    """Render and analyse the candidate ``design_path`` and compare it with the baseline.

    ``given``: options replacing the baseline's for the candidate (see the
    module docstring). ``out_dir``: where to write ``report.json``,
    ``report.txt``, the candidate's images and the heat maps (None: nothing
    written). ``junit``: a path for JUnit XML.
    """
    t0 = time.perf_counter()
    if out_dir is not None:
        from ..fileio import check_replaceable

        check_replaceable(out_dir, "report.json")
    folder = Path(baseline_dir)
    doc = bl.read(folder)
    given = {k: v for k, v in (given or {}).items() if v is not None}
    base_opts = _options_from_baseline(doc, folder)
    opts = normalize_options(dict(base_opts, **given))
    b_opts = doc["options"]
    if opts["spp"] != b_opts["spp"]:
        raise RegressionInputError(f"--spp = {opts['spp']}: the baseline {folder} was rendered at "
                                   f"{b_opts['spp']} spp (its noise model holds for that spp); re-create it "
                                   "with --update")
    if opts["resolution"] != b_opts["resolution"]:
        raise RegressionInputError(f"--resolution = {','.join(map(str, opts['resolution']))}: the baseline "
                                   f"{folder} is {b_opts['resolution'][0]},{b_opts['resolution'][1]} px")
    if len(opts["focus_mm"]) != len(b_opts["focus_mm"]):
        raise RegressionInputError(f"--focus-mm = {','.join(f'{f:g}' for f in opts['focus_mm'])}: the baseline "
                                   f"{folder} has {len(b_opts['focus_mm'])} focus distance(s)")
    seeds = [opts["seed"], opts["seed"] + 1] if "seed" in given else list(doc["seeds"])
    tol = doc["tolerances"]
    base_imgs = bl.load_images(folder, doc)
    design = load_design(design_path, opts)
    r = render(design, opts, seeds, log)
    checks = image_checks(base_imgs, r.images, b_opts["focus_mm"], r.options["focus_mm"], tol)
    checks += render_checks(doc["render"], r.info, tol)
    metrics = {}
    if b_opts.get("metrics", True) and doc.get("metrics"):
        metrics = design_metrics(design, opts)
        checks += metric_checks(doc["metrics"], metrics, tol)
    changed_opts = {k: {"baseline": b_opts.get(k), "candidate": r.options.get(k)}
                    for k in ("focus_mm", "cdp_mm", "pupil_mm", "eye", "mla_cells", "optics", "tessellation", "set")
                    if r.options.get(k) != b_opts.get(k)}
    if Path(opts["content"]).resolve() != Path(base_opts["content"]).resolve():
        changed_opts["content"] = {"baseline": b_opts["content"], "candidate": opts["content"]}
    same_design = Path(design_path).is_file() and _sha256(design_path) == doc["design"].get("sha256")
    report = {
        "design": str(design_path), "baseline": str(folder), "created": _now(),
        "baseline_created": doc.get("created"), "design_file_unchanged": same_design,
        "seeds": {"baseline": doc["seeds"], "candidate": seeds,
                  "common_random_numbers": list(seeds) == list(doc["seeds"])},
        "spp": opts["spp"], "resolution": r.options["resolution"], "options_changed": changed_opts,
        "tolerances": tol, "noise_model": "cross-seed products, self-normalised tile sums (lfsim.regression.noise)",
        "failed": any(c.failed for c in checks), "checks": [c.as_dict() for c in checks],
        "render_s": round(r.seconds, 3),
    }
    result = RegressionResult(checks, report)
    report["summary"] = result.summary()
    report["table"] = result.table()
    report["total_s"] = round(time.perf_counter() - t0, 3)
    if out_dir is not None:
        result.files = write_outputs(out_dir, result, base_imgs, r, b_opts["focus_mm"], heatmaps)
    if junit is not None:
        from . import junit as ju

        ju.write(junit, checks, f"lfsim regress {Path(str(design_path)).name} vs {folder}",
                 {"design": design_path, "baseline": folder, "spp": opts["spp"],
                  "seeds": ",".join(map(str, seeds))}, report["total_s"], report["created"])
        result.files["junit"] = str(junit)
    return result


def _label(kind: str, f_base: float, f_cand: float) -> str:
    if abs(f_base - f_cand) < 1e-9:
        return f"{kind} {f_base:g} mm"
    return f"{kind} {f_base:g} mm (candidate {f_cand:g} mm)"


def image_checks(base: dict, cand: dict, focus_b, focus_c, tol: dict) -> list[Check]:
    """Change, detail and (display) error against the natural view of every retinal image."""
    z_max = tol["z_max"]
    out = []
    for i, (fb, fc) in enumerate(zip(focus_b, focus_c)):
        for kind in KINDS:
            B, C = tuple(base[(kind, i)][:2]), tuple(cand[(kind, i)][:2])
            if B[0].shape != C[0].shape:
                raise RegressionInputError(f"{kind} at {fb:g} mm: candidate {C[0].shape[1]}x{C[0].shape[0]} px, "
                                           f"baseline {B[0].shape[1]}x{B[0].shape[0]} px")
            label = _label(kind, fb, fc)
            ch = noise.change(B, C, z_max, tol["tile_px"])
            t = max(ch.threshold, tol["image_change_floor"])
            out.append(Check(f"{label}: image", "image", "rms change / mean", ch.baseline, ch.candidate, ch.value, t,
                             "changed" if ch.value > t else "ok", "%", ch.z, "either",
                             "baseline/candidate: seed-to-seed RMS noise of one render (fraction of the mean)", "%"))
            de = noise.detail(B, C, z_max, tol["detail_tile_px"])
            t = max(de.threshold, tol["detail_floor"])
            st = "worse" if de.value < -t else "better" if de.value > t else "ok"
            out.append(Check(f"{label}: detail", "image", "band-pass energy", de.baseline, de.candidate, de.value, t,
                             st, "%", de.z, "higher",
                             "noise-free band-pass (DoG 1, 2.5 px) energy per pixel; negative change = blurrier"))
            if kind == "display":
                NB, NC = tuple(base[("natural", i)][:2]), tuple(cand[("natural", i)][:2])
                er = noise.error_vs(NB, B, NC, C, z_max, tol["tile_px"])
                t = max(er.threshold, tol["error_floor"])
                st = "worse" if er.value > t else "better" if er.value < -t else "ok"
                rng = max(float(np.max(NB[0]) - np.min(NB[0])), 1e-12)
                out.append(Check(f"{label}: error vs natural", "image", "noise-free PSNR vs natural view",
                                 noise.noise_free_psnr(er.baseline, rng), noise.noise_free_psnr(er.candidate, rng),
                                 er.value, t, st, "%", er.z, "lower",
                                 "change = relative change of the noise-free MSE against the natural view", "dB"))
    return out


def _tol(tol: dict, name: str) -> tuple[float, float]:
    per = (tol.get("per_check") or {}).get(name, {})
    return float(per.get("rel", tol["metric_rel"])), float(per.get("abs", tol["metric_abs"]))


def render_checks(base: dict, cand: dict, tol: dict) -> list[Check]:
    """The render's field of view and tunable-lens power (deterministic)."""
    out = []
    for j, (b, c) in enumerate(zip(base["fov_deg"], cand["fov_deg"])):
        name = f"render fov_deg[{j}]"
        out.append(numeric_check(name, "render", b, c, "either", *_tol(tol, name), unit="deg"))
    name = "render tunable_power_diopters"
    out.append(numeric_check(name, "render", base.get("tunable_power_diopters"), cand.get("tunable_power_diopters"),
                             "either", *_tol(tol, name), unit="D"))
    return out


def metric_checks(base: dict, cand: dict, tol: dict) -> list[Check]:
    """Every design metric of the baseline against the candidate's (deterministic, tight tolerances)."""
    out = []
    for key in list(base) + [k for k in cand if k not in base]:
        b, c = base.get(key), cand.get(key)
        direction = (b or c)["direction"]
        name = f"metric {key}"
        out.append(numeric_check(name, "metric", b["value"] if b else None, c["value"] if c else None,
                                 direction, *_tol(tol, name)))
    return out


def write_outputs(out_dir, result: RegressionResult, base_imgs: dict, r: Rendered, focus_b, heatmaps=True) -> dict:
    """report.json, report.txt, the candidate's images and the heat maps, in a folder
    replaced as a whole on success (see :func:`lfsim.fileio.atomic_dir`)."""
    from ..fileio import atomic_dir

    with atomic_dir(out_dir, "report.json") as out:
        return _write_outputs(out, result, base_imgs, r, focus_b, heatmaps)


def _write_outputs(out: Path, result: RegressionResult, base_imgs: dict, r: Rendered, focus_b, heatmaps) -> dict:
    from ..analysis.compare import compare_images, heatmap, json_safe
    from ..fileio import write_json, write_text
    from ..render.focal_stack import write_exr

    files = {"report_json": "report.json", "report_txt": "report.txt", "images": [], "heatmaps": []}
    plain = []
    for (kind, i), imgs in sorted(r.images.items()):
        f = r.options["focus_mm"][i]
        for seed, img in zip(result.doc["seeds"]["candidate"], imgs):
            name = bl.image_name(kind, f, seed)
            write_exr(out / name, img, {"kind": kind, "focus_mm": f, "seed": seed, "spp": r.options["spp"]})
            files["images"].append(name)
        b_mean = np.mean(np.asarray(base_imgs[(kind, i)], np.float64), axis=0)
        c_mean = np.mean(np.asarray(imgs, np.float64), axis=0)
        cmp = compare_images(b_mean, c_mean, ["R", "G", "B"])
        label = _label(kind, focus_b[i], f)
        plain.append({"image": label, **{k: cmp[k] for k in ("psnr", "ssim", "rmse", "rmse_channels", "max_abs")}})
        if heatmaps:
            status = [c.status for c in result.checks if c.name.startswith(label + ":")]
            worst = next((s for s in ("worse", "changed", "better") if s in status), "ok")
            name = f"heatmaps/{kind}_{focus_b[i]:g}mm.png"
            heatmap(b_mean, c_mean, out / name,
                    f"{label}: {worst}; mean of the seeds, PSNR {cmp['psnr']:.1f} dB, SSIM {cmp['ssim']:.3f}",
                    labels=("baseline", "candidate"))
            files["heatmaps"].append(name)
    result.doc["plain_comparison"] = json_safe(plain)
    result.doc["files"] = files
    write_json(out / "report.json", json_safe(result.doc))
    write_text(out / "report.txt", text_report(result))
    return files


def text_report(result: RegressionResult) -> str:
    d = result.doc
    lines = [f"lfsim regress {d['design']} against {d['baseline']} ({d['spp']} spp, "
             f"{d['resolution'][0]}x{d['resolution'][1]} px, seeds {d['seeds']['candidate']} vs "
             f"{d['seeds']['baseline']})", result.summary()]
    for k, v in d["options_changed"].items():
        lines.append(f"  candidate option {k}: {v['candidate']} (baseline {v['baseline']})")
    lines += ["", result.table(include_ok=True), ""]
    return "\n".join(lines)
