"""Ray-trace throughput of lfsim (Dr.Jit) against NumPy and optiland baselines.

Usage::

    .venv/bin/python benchmarks/trace_throughput.py                 # 1e5, 1e6, 4e6 rays
    .venv/bin/python benchmarks/trace_throughput.py --sizes 1e5     # quick run
    .venv/bin/python benchmarks/trace_throughput.py --scenes my.toml --out /tmp/t.json

For every design (default ``scenes/cooke_triplet.toml`` and
``scenes/freeform_prism.toml``; a missing file is skipped with a note) and ray
count N it measures rays per second of

* lfsim forward trace, float64 and float32;
* lfsim forward + reverse: the gradient of a spot-size-like scalar
  (Σ x² + y² of the image positions of the valid rays) with respect to the
  whole packed parameter array (``dr.enable_grad(P)``, ``dr.backward``),
  float64 and float32;
* lfsim end to end through its numpy API, float64: ``design.trace`` with
  (N, 3) numpy arrays in and numpy results out, every conversion included
  (the column a user of the Python API gets; ``kernel_share`` is the
  kernel call's time over it);
* the NumPy float64 baseline (``benchmarks/numpy_tracer.py``, an independent
  vectorized implementation of the same model);
* optiland (NumPy back end, float64) for the Cooke triplet only, built from
  the same prescription with constant indices equal to lfsim's at the
  wavelength (``--optiland-glass catalog`` uses optiland's SK16/F2 instead).

Rays: a realistic bundle, uniformly random over the paraxial entrance pupil,
cycling over the design's fields, at the primary wavelength (``field_rays``
with first-order pupil data; a fallback pupil is used when first-order
analysis fails and is noted in the JSON).

Timing: a warm-up call (for lfsim it includes tracing the Python code to
Dr.Jit IR and compiling the kernels, reported as ``first_call_s`` with the
kernels' codegen/compile times from Dr.Jit's kernel history), then the best
of ``--repeats`` calls. lfsim calls end with ``dr.eval`` of everything they
return and ``dr.sync_thread()``, so a timing includes the kernel run and the
Python-side IR construction. The baselines have nothing to compile; their
warm-up call uses at most 1e4 rays. By default Dr.Jit's on-disk kernel cache is a
fresh private directory (so first-call times are real compile times); pass
``--warm-cache`` to use ``~/.drjit``. Baselines above ``--numpy-max-rays`` /
``--optiland-max-rays`` rays are timed on a prefix of that size (the bundle
is interleaved over fields and random in the pupil, so a prefix is a fair
sample) and their throughput is taken as that of the prefix; the JSON says so.

Agreement: at every size the NumPy baseline's positions are compared with
lfsim float64 over rays that are OK in both (and the status codes ray by
ray); lfsim float32 and optiland are compared with lfsim float64 too.

Output: a markdown table on stdout and a JSON file (default
``benchmarks/results/trace_throughput.json``), written atomically.
"""

from __future__ import annotations

import argparse
import gc
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENES = ["scenes/cooke_triplet.toml", "scenes/freeform_prism.toml"]
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "trace_throughput.json"

COLUMNS = [
    ("lfsim_f64_fwd", "lfsim f64 fwd"),
    ("lfsim_f32_fwd", "lfsim f32 fwd"),
    ("lfsim_f64_fwdrev", "lfsim f64 fwd+rev"),
    ("lfsim_f32_fwdrev", "lfsim f32 fwd+rev"),
    ("lfsim_f64_api", "lfsim f64 design.trace"),
    ("numpy_f64_fwd", "numpy f64 fwd"),
    ("optiland_f64_fwd", "optiland fwd"),
]

# The Cooke triplet as given to optiland (radius, thickness, material, stop).
TRIPLET = [
    (22.01359, 3.25896, "SK16", False),
    (-435.76044, 6.00755, None, False),
    (-22.21328, 0.99997, "F2", False),
    (20.29192, 4.75041, None, True),
    (79.68360, 2.95208, "SK16", False),
    (-18.39533, 42.20778, None, False),
]
OPTILAND_CATALOG = {"SK16": ("SK16", "hikari"), "F2": ("F2", "schott")}


# ----------------------------------------------------------------- helpers
def _size(text: str) -> int:
    v = float(text)
    if not (v >= 1 and v == int(v)):
        raise argparse.ArgumentTypeError(f"a ray count must be a positive integer, got {text!r}")
    return int(v)


def _sizes(text: str) -> list[int]:
    return [_size(t) for t in text.replace(" ", "").split(",") if t]


def _finite(x):
    """JSON-safe copy: non-finite floats become None, numpy scalars become Python."""
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, (np.floating, float)):
        x = float(x)
        return x if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS counter (VmHWM) of this process (Linux)."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


_MAX_RSS_MB = [0.0]
_LAST_CPU = [float("nan")]  # process CPU time / wall time of the last best call


def _git_state() -> dict | None:
    """Commit and dirty files of the repository the benchmark runs from."""
    import subprocess

    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True, timeout=10, check=True).stdout.split("\n")
        return {"commit": head, "modified": [ln[3:] for ln in dirty if ln.strip()]}
    except (OSError, subprocess.SubprocessError):
        return None


def _loadavg():
    try:
        return list(os.getloadavg())
    except OSError:
        return None


def _rss_mb(field: str = "VmHWM") -> float | None:
    """Peak (VmHWM, since the last reset) or current (VmRSS) resident memory in MB."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    mb = int(line.split()[1]) / 1024.0
                    _MAX_RSS_MB[0] = max(_MAX_RSS_MB[0], mb)
                    return mb
    except OSError:
        pass
    return None


def _timed(fn, repeats: int, setup=None, warmup=None):
    """Warm-up call, then the best of ``repeats`` calls; ``setup()`` is not timed.

    Returns (first_call_s, best_s, all_s, last_result).
    """
    if warmup is not None:  # a cheaper warm-up (no compilation to amortize)
        t0 = time.perf_counter()
        res = warmup()
    else:
        arg = setup() if setup else None
        t0 = time.perf_counter()
        res = fn(arg) if setup else fn()
    first = time.perf_counter() - t0
    del res
    times = []
    cpu = []
    res = None
    for _ in range(repeats):
        res = None
        gc.collect()
        arg = setup() if setup else None
        c0 = time.process_time()
        t0 = time.perf_counter()
        res = fn(arg) if setup else fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    _LAST_CPU[0] = cpu[int(np.argmin(times))] / min(times)
    return first, min(times), times, res


def _kernel_summary(history) -> dict:
    """Summary of Dr.Jit kernel-history entries (times in seconds)."""
    jit = [h for h in history if str(h.get("type", "")).endswith("JIT")]
    return {
        "kernels_launched": len(jit),
        "compiled": sum(1 for h in jit if not h.get("cache_hit") and not h.get("cache_disk")),
        "from_disk_cache": sum(1 for h in jit if h.get("cache_disk")),
        "codegen_s": sum(h.get("codegen_time", 0.0) for h in jit) * 1e-3,
        "backend_compile_s": sum(h.get("backend_time", 0.0) for h in jit if not h.get("cache_hit")) * 1e-3,
        "execution_s": sum(h.get("execution_time", 0.0) for h in jit) * 1e-3,
        "operations": sum(h.get("operation_count", 0) for h in jit),
    }


# --------------------------------------------------------------------- rays
def make_rays(design, n: int, wavelength_nm: float, seed: int = 0):
    """A bundle of ``n`` rays over the entrance pupil, interleaved over the fields.

    Returns ``(origins (n, 3), directions (n, 3), info)``.
    """
    from lfsim.optics.sampling import field_rays

    system = design.system
    info = {"fields": list(system.fields), "field_type": system.field_type,
            "pupil": "uniform random in the entrance pupil disc", "seed": seed}
    fo = None
    try:
        fo = design.first_order(wavelength_nm)
        if not (math.isfinite(fo.entrance_pupil_diameter) and fo.entrance_pupil_diameter > 0
                and math.isfinite(fo.entrance_pupil_position)):
            raise ValueError(f"entrance pupil {fo.entrance_pupil_diameter}, {fo.entrance_pupil_position}")
        info["pupil_from"] = f"first-order ({fo.method})"
    except Exception as e:  # fall back to the stop / first surface
        from numpy_tracer import surface_frames

        frames = surface_frames(system)
        k = system.stop_index if system.stop_index is not None else 0
        ap = system.surfaces[k].aperture
        if system.aperture_type == "epd" and system.aperture_value > 0:
            diam = system.aperture_value
        elif ap is not None:
            diam = 2.0 * ap.extent()
        else:
            diam = 1.0
        fo = SimpleNamespace(entrance_pupil_diameter=diam, entrance_pupil_position=float(frames[k][1][2]))
        info["pupil_from"] = f"fallback (first-order failed: {type(e).__name__}: {e})"
    info["entrance_pupil_diameter"] = fo.entrance_pupil_diameter
    info["entrance_pupil_position"] = fo.entrance_pupil_position

    rng = np.random.default_rng(seed)
    r = np.sqrt(rng.random(n))
    a = 2.0 * math.pi * rng.random(n)
    pupil = np.stack([r * np.cos(a), r * np.sin(a)], axis=1)
    which = np.arange(n) % len(system.fields)
    O = np.empty((n, 3))
    D = np.empty((n, 3))
    for f_i, f in enumerate(system.fields):
        sel = which == f_i
        O[sel], D[sel] = field_rays(system, fo, f, pupil[sel])
    return O, D, info


# --------------------------------------------------------------- optiland
def build_optiland_triplet(system, wavelength_nm: float, glass: str):
    """The Cooke triplet in optiland (apertures = lfsim's semi-diameters)."""
    from optiland.materials import IdealMaterial
    from optiland.optic import Optic

    try:
        from optiland.physical_apertures import RadialAperture
    except ImportError:  # pragma: no cover - older optiland
        RadialAperture = None
    lens = Optic()
    lens.surfaces.add(index=0, radius=np.inf, thickness=np.inf)
    surf = system.surfaces
    for i, (radius, thick, mat, stop) in enumerate(TRIPLET):
        kw = {}
        if mat is not None:
            if glass == "catalog":
                kw["material"] = OPTILAND_CATALOG[mat]
            else:  # constant index = lfsim's index of the same glass at the wavelength
                kw["material"] = IdealMaterial(n=float(surf[i].material.index(wavelength_nm)))
        if RadialAperture is not None and i < len(surf) and surf[i].semi_diameter:
            kw["aperture"] = RadialAperture(r_max=float(surf[i].semi_diameter))
        lens.surfaces.add(index=i + 1, radius=radius, thickness=thick, is_stop=stop, **kw)
    lens.surfaces.add(index=len(TRIPLET) + 1)
    lens.set_aperture(aperture_type="EPD", value=10.0)
    lens.fields.set_type(field_type="angle")
    for f in system.fields:
        lens.fields.add(y=float(f))
    lens.wavelengths.add(value=wavelength_nm * 1e-3, is_primary=True)
    return lens


def triplet_matches(system) -> str | None:
    """None if the design is the triplet given to optiland, else why not."""
    s = system.surfaces
    if len(s) != len(TRIPLET) + 1:
        return f"{len(s)} surfaces, expected {len(TRIPLET) + 1}"
    for i, (radius, thick, mat, stop) in enumerate(TRIPLET):
        if abs(s[i].curvature - 1.0 / radius) > 1e-12 or abs(s[i].thickness - thick) > 1e-9:
            return f"surface {i} differs"
        if (mat or "air").upper() != s[i].material.name.upper() or bool(stop) != bool(s[i].stop):
            return f"surface {i} material/stop differs"
    return None


# ------------------------------------------------------------------ lfsim
class LfsimCase:
    """Dr.Jit rays and parameters for one design, precision and ray count."""

    def __init__(self, design, precision: str, cols, wavelength_nm: float):
        import drjit as dr

        from lfsim.optics.tracer import RayState

        self.dr = dr
        self.tr = design.tracer(precision)
        T = self.T = self.tr.T
        self.values = np.asarray(design.system.parameter_values(wavelength_nm), dtype=np.float64)
        self.P = self._array(self.values)
        ox, oy, oz, dx, dy, dz = (self._array(c) for c in cols)
        self.rays = RayState(T.Array3(ox, oy, oz), T.Array3(dx, dy, dz))
        dr.eval(self.P, self.rays.p, self.rays.d)
        dr.sync_thread()

    def _array(self, a):
        """An evaluated Dr.Jit-owned copy of numpy ``a``.

        Dr.Jit maps numpy buffers without copying (``dr.copy`` of such an array
        keeps the numpy pointer too) and a kernel that reads a buffer bakes in
        its alignment, so kernels reading numpy memory may recompile whenever
        numpy allocates differently. ``x * opaque(1)`` (exact, keeps −0.0) is
        evaluated into Dr.Jit's own aligned memory.
        """
        dr, T = self.dr, self.T
        x = T.Float(np.ascontiguousarray(a, dtype=T.np_dtype)) * dr.opaque(T.Float, 1.0)
        dr.eval(x)
        return x

    def forward(self):
        dr = self.dr
        with dr.suspend_grad():
            out = self.tr.trace(self.P, self.rays)
            dr.eval(out.p, out.d, out.status, out.opl)
        dr.sync_thread()
        return out

    def forward_reverse(self):
        dr = self.dr
        P = self._array(self.values)
        dr.enable_grad(P)
        out = self.tr.trace(P, self.rays)
        ok = out.status == 0
        # Symbolic reduction: the loss stays lazy, so its forward evaluation is
        # fused with the reverse pass instead of costing a kernel of its own.
        loss = dr.sum(dr.select(ok, dr.square(out.p.x) + dr.square(out.p.y), 0.0), mode="symbolic")
        dr.backward(loss)
        grad = dr.grad(P)
        dr.eval(loss, grad)
        dr.sync_thread()
        return loss, grad


def _np3(v) -> np.ndarray:
    return np.stack([np.asarray(v.x), np.asarray(v.y), np.asarray(v.z)], axis=1).astype(np.float64)


# ------------------------------------------------------------- benchmarks
def bench_scene(path: Path, args, log) -> dict:
    import drjit as dr
    from numpy_tracer import trace_numpy

    import lfsim

    design = lfsim.load(path)
    system = design.system
    lam = system.primary_wavelength_nm
    n_max = max(args.sizes)
    t0 = time.perf_counter()
    O, D, ray_info = make_rays(design, n_max, lam, seed=args.seed)
    ray_info["generation_s"] = time.perf_counter() - t0
    out = {"scene": str(path), "name": system.name, "wavelength_nm": lam,
           "surfaces": len(system.surfaces),
           "newton_surfaces": sum(1 for s in system.surfaces if s.needs_newton and s.interaction != "break"),
           "n_params": len(system.parameter_names()), "rays": ray_info, "sizes": {}, "notes": []}

    # Which baselines apply.
    numpy_ok = True
    try:
        trace_numpy(system, O[:8], D[:8], lam)
    except NotImplementedError as e:
        numpy_ok = False
        out["notes"].append(f"numpy baseline skipped: {e}")
    optiland_lens = None
    if getattr(args, "optiland_unavailable", None):
        out["notes"].append(args.optiland_unavailable)
    elif args.no_optiland:
        out["notes"].append("optiland skipped (--no-optiland)")
    elif Path(path).stem != "cooke_triplet":
        out["notes"].append("optiland column only for the Cooke triplet")
    elif (why := triplet_matches(system)) is not None:
        out["notes"].append(f"optiland skipped: design is not the reference triplet ({why})")
    else:
        try:
            import optiland

            optiland_lens = build_optiland_triplet(system, lam, args.optiland_glass)
            out["optiland"] = {"version": getattr(optiland, "__version__", None) or args.optiland_version,
                               "glass": args.optiland_glass, "apertures": "RadialAperture(semi_diameter)",
                               "backend": "numpy float64", "call": "lens.surfaces.trace(rays, record=False)"}
        except ImportError as e:
            out["notes"].append(f"optiland not installed ({e}); column skipped")

    for n in sorted(args.sizes):
        log(f"  N = {n:.0e}")
        cols = [O[:n, 0], O[:n, 1], O[:n, 2], D[:n, 0], D[:n, 1], D[:n, 2]]
        res: dict = {}
        lf64 = None
        lf32 = None
        for prec in ("float64", "float32"):
            tag = "f64" if prec == "float64" else "f32"
            dr.flush_malloc_cache()
            case = LfsimCase(design, prec, cols, lam)
            for mode, fn in (("fwd", case.forward), ("fwdrev", case.forward_reverse)):
                key = f"lfsim_{tag}_{mode}"
                gc.collect()
                dr.flush_malloc_cache()
                _reset_peak_rss()
                dr.kernel_history_clear()
                first, best, times, r = _timed_lfsim(fn, _repeats(args.repeats, n))
                rec = {"rays": n, "timed_rays": n, "first_call_s": first["time"],
                       "first_call_kernels": first["kernels"], "best_s": best,
                       "repeats_s": times, "rays_per_s": n / best,
                       "kernels_per_call": r["kernels"], "peak_rss_mb": _rss_mb(),
                       "cpu_per_wall": _LAST_CPU[0]}
                if mode == "fwd":
                    o = r["result"]
                    st = np.asarray(o.status).astype(np.int64)
                    rec["ok_fraction"] = float(np.mean(st == 0))
                    rec["status_counts"] = np.bincount(st, minlength=7).tolist()
                    snap = (_np3(o.p), st, np.asarray(o.opl).astype(np.float64), _np3(o.d))
                    if prec == "float64":
                        lf64 = snap
                    else:
                        lf32 = snap
                else:
                    loss, grad = r["result"]
                    g = np.asarray(grad, dtype=np.float64)
                    rec["loss"] = float(np.asarray(loss)[0])
                    rec["grad_finite"] = bool(np.all(np.isfinite(g)))
                    rec["grad_norm"] = float(np.linalg.norm(g))
                    rec["grad_nonzero"] = int(np.count_nonzero(g))
                res[key] = rec
                del r
                log(f"    {key:18s} first {first['time']:7.3f} s  best {best:8.4f} s  "
                    f"{n / best / 1e6:8.3f} M rays/s  peak RSS {rec['peak_rss_mb'] or 0:7.0f} MB  "
                    f"cpu/wall {rec['cpu_per_wall']:.2f}")
            del case
        dr.flush_malloc_cache()

        # lfsim end to end through its numpy API (design.trace: (N, 3) numpy in, numpy out).
        o_n, d_n = np.ascontiguousarray(O[:n]), np.ascontiguousarray(D[:n])
        gc.collect()
        dr.flush_malloc_cache()
        _reset_peak_rss()
        first, best, times, r = _timed(lambda: design.trace(o_n, d_n, wavelength_nm=lam),  # noqa: F821 (del below)
                                       _repeats(args.repeats, n))
        res["lfsim_f64_api"] = {"rays": n, "timed_rays": n, "first_call_s": first, "best_s": best,
                                "repeats_s": times, "rays_per_s": n / best, "peak_rss_mb": _rss_mb(),
                                "cpu_per_wall": _LAST_CPU[0],
                                "kernel_share": res["lfsim_f64_fwd"]["best_s"] / best}
        api_dp = float(np.abs(r.positions - lf64[0]).max())
        log(f"    {'lfsim_f64_api':18s} first {first:7.3f} s  best {best:8.4f} s  "
            f"{n / best / 1e6:8.3f} M rays/s  (kernel call / end to end {res['lfsim_f64_api']['kernel_share']:.2f};"
            f" max|dp| vs the kernel call {api_dp:.3g} mm)")
        del r, o_n, d_n

        agree: dict = {"lfsim_api_vs_kernel_max_abs_dposition_mm": api_dp}
        # lfsim float32 vs float64.
        okb = (lf64[1] == 0) & (lf32[1] == 0)
        agree["lfsim_f32_vs_f64"] = {
            "rays_compared": int(okb.sum()),
            "status_mismatches": int(np.sum(lf64[1] != lf32[1])),
            "max_abs_dposition_mm": float(np.abs(lf64[0][okb] - lf32[0][okb]).max()) if okb.any() else None,
        }
        del lf32

        # NumPy baseline.
        if numpy_ok:
            m = min(n, args.numpy_max_rays)
            o_m, d_m = O[:m], D[:m]
            gc.collect()
            _reset_peak_rss()
            first, best, times, r = _timed(lambda: trace_numpy(system, o_m, d_m, lam), _repeats(args.repeats, m),
                                           warmup=lambda: trace_numpy(system, o_m[:min(m, 10000)],
                                                                      d_m[:min(m, 10000)], lam))
            res["numpy_f64_fwd"] = {
                "rays": n, "timed_rays": m, "scaled_from_subset": m < n,
                "note": (f"timed on the first {m} rays; rays_per_s is that subset's, "
                         f"best_s_scaled = best_s * {n}/{m}") if m < n else "",
                "warmup_rays": min(m, 10000), "first_call_s": first, "best_s": best,
                "best_s_scaled": best * n / m, "repeats_s": times, "rays_per_s": m / best,
                "peak_rss_mb": _rss_mb(), "threads": 1, "cpu_per_wall": _LAST_CPU[0],
            }
            p_np, d_np, st_np, opl_np = r
            p64, st64, opl64, d64 = (a[:m] for a in lf64)
            okb = (st64 == 0) & (st_np == 0)
            agree["numpy_vs_lfsim_f64"] = {
                "rays_compared": int(okb.sum()), "of": m,
                "status_mismatches": int(np.sum(st64 != st_np)),
                "max_abs_dposition_mm": float(np.abs(p64[okb] - p_np[okb]).max()) if okb.any() else None,
                "max_abs_ddirection": float(np.abs(d64[okb] - d_np[okb]).max()) if okb.any() else None,
                "max_abs_dopl_mm": float(np.abs(opl64[okb] - opl_np[okb]).max()) if okb.any() else None,
                "max_abs_dposition_failed_rays_mm": (
                    float(np.abs(p64[~okb] - p_np[~okb]).max()) if (~okb).any() else None),
            }
            log(f"    {'numpy_f64_fwd':18s} first {first:7.3f} s  best {best:8.4f} s  "
                f"{m / best / 1e6:8.3f} M rays/s  ({m} rays timed)  "
                f"max|dp| vs lfsim {agree['numpy_vs_lfsim_f64']['max_abs_dposition_mm']:.3g} mm, "
                f"status mismatches {agree['numpy_vs_lfsim_f64']['status_mismatches']}")
            del r, p_np, d_np, st_np, opl_np

        # optiland.
        if optiland_lens is not None:
            from optiland.rays import RealRays

            m = min(n, args.optiland_max_rays) if args.optiland_max_rays else n
            w = lam * 1e-3

            def setup(k=m):
                return RealRays(O[:k, 0].copy(), O[:k, 1].copy(), O[:k, 2].copy(),
                                D[:k, 0].copy(), D[:k, 1].copy(), D[:k, 2].copy(),
                                np.ones(k), np.full(k, w))

            def run(rays):
                optiland_lens.surfaces.trace(rays, record=False)
                return rays

            gc.collect()
            _reset_peak_rss()
            wm = min(m, 10000)
            first, best, times, rays = _timed(run, _repeats(args.repeats, m), setup=setup,
                                              warmup=lambda: run(setup(wm)))
            res["optiland_f64_fwd"] = {
                "rays": n, "timed_rays": m, "scaled_from_subset": m < n,
                "note": (f"timed on the first {m} rays" if m < n else "")
                + "; RealRays construction excluded from the timing",
                "warmup_rays": wm, "first_call_s": first, "best_s": best, "best_s_scaled": best * n / m,
                "repeats_s": times, "rays_per_s": m / best, "peak_rss_mb": _rss_mb(),
                "cpu_per_wall": _LAST_CPU[0],
            }
            p_o = np.stack([np.asarray(rays.x), np.asarray(rays.y), np.asarray(rays.z)], axis=1)
            inten = np.asarray(rays.i)
            okb = (lf64[1][:m] == 0) & (inten > 0)
            agree["optiland_vs_lfsim_f64"] = {
                "rays_compared": int(okb.sum()), "of": m,
                "vignetting_mismatches": int(np.sum((lf64[1][:m] == 0) != (inten > 0))),
                "max_abs_dposition_mm": float(np.abs(lf64[0][:m][okb] - p_o[okb]).max()) if okb.any() else None,
                "glass": args.optiland_glass,
            }
            log(f"    {'optiland_f64_fwd':18s} first {first:7.3f} s  best {best:8.4f} s  "
                f"{m / best / 1e6:8.3f} M rays/s  ({m} rays timed)  "
                f"max|dp| vs lfsim {agree['optiland_vs_lfsim_f64']['max_abs_dposition_mm']:.3g} mm")
            del rays, p_o
        del lf64
        gc.collect()

        ratios = {}

        def thr(k):
            return res[k]["rays_per_s"] if k in res else None

        if thr("numpy_f64_fwd"):
            ratios["lfsim_f64_fwd_over_numpy"] = thr("lfsim_f64_fwd") / thr("numpy_f64_fwd")
        if thr("optiland_f64_fwd"):
            ratios["lfsim_f64_fwd_over_optiland"] = thr("lfsim_f64_fwd") / thr("optiland_f64_fwd")
            ratios["lfsim_f64_api_over_optiland"] = thr("lfsim_f64_api") / thr("optiland_f64_fwd")
        for tag in ("f64", "f32"):
            t_fr, t_f = res[f"lfsim_{tag}_fwdrev"]["best_s"], res[f"lfsim_{tag}_fwd"]["best_s"]
            ratios[f"fwdrev_over_fwd_time_{tag}"] = t_fr / t_f
            # The reverse pass alone: (forward + reverse) minus one forward.
            ratios[f"rev_over_fwd_time_{tag}"] = (t_fr - t_f) / t_f
        ratios["lfsim_f32_over_f64_fwd"] = thr("lfsim_f32_fwd") / thr("lfsim_f64_fwd")
        out["sizes"][str(n)] = {"results": res, "ratios": ratios, "agreement": agree,
                                "loadavg_after": _loadavg()}
    return out


def _repeats(base: int, n: int) -> int:
    """Best-of count: ``--repeats``, raised for short calls (≈1e6 rays in all, at most 20)
    so millisecond timings are not at the mercy of one scheduler hiccup."""
    return max(base, min(20, int(1e6 // max(n, 1))))


def _timed_lfsim(fn, repeats):
    """Like :func:`_timed` for lfsim calls, with Dr.Jit kernel statistics."""
    import drjit as dr

    dr.kernel_history_clear()
    t0 = time.perf_counter()
    r = fn()
    first = time.perf_counter() - t0
    first_k = _kernel_summary(dr.kernel_history())
    del r
    times = []
    cpu = []
    r = None
    for _ in range(repeats):
        r = None
        gc.collect()
        dr.kernel_history_clear()
        c0 = time.process_time()
        t0 = time.perf_counter()
        r = fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        k = _kernel_summary(dr.kernel_history())
    _LAST_CPU[0] = cpu[int(np.argmin(times))] / min(times)
    return ({"time": first, "kernels": first_k}, min(times), times,
            {"result": r, "kernels": {"launched": k["kernels_launched"], "execution_s": k["execution_s"]}})


# ------------------------------------------------------------------ report
def _fmt(v, digits=3):
    if v is None:
        return "—"
    if v >= 100:
        return f"{v:.0f}"
    return f"{v:.{digits}g}"


def markdown(report: dict) -> str:
    lines = []
    head = ["scene", "N"] + [c[1] for c in COLUMNS] + [
        "f64 fwd / numpy", "f64 fwd / optiland", "design.trace / optiland", "(fwd+rev)/fwd f64", "(fwd+rev)/fwd f32",
        "rev/fwd f64", "rev/fwd f32"]
    lines.append(f"Throughput in M rays/s (best of {report['settings']['repeats']}; * = baseline timed on a "
                 f"{report['settings']['numpy_max_rays']:.0e}-ray prefix);"
                 " ratios: speed-up (throughput ratio) and gradient cost (time ratio;"
                 " rev = (fwd+rev) − fwd, the reverse pass alone).")
    lines.append("")
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "|".join(["---"] * 2 + ["---:"] * (len(head) - 2)) + "|")
    for sc in report["scenes"]:
        if "skipped" in sc:
            lines.append(f"| {Path(sc['scene']).stem} | — | " + " | ".join(["skipped"] + [""] * (len(head) - 3)) + " |")
            continue
        for n, sz in sc["sizes"].items():
            row = [Path(sc["scene"]).stem, f"{int(n):.0e}"]
            for key, _ in COLUMNS:
                r = sz["results"].get(key)
                if r is None:
                    row.append("—")
                else:
                    row.append(_fmt(r["rays_per_s"] / 1e6) + ("*" if r.get("scaled_from_subset") else ""))
            rt = sz["ratios"]
            row += [_fmt(rt.get("lfsim_f64_fwd_over_numpy")), _fmt(rt.get("lfsim_f64_fwd_over_optiland")),
                    _fmt(rt.get("lfsim_f64_api_over_optiland")),
                    _fmt(rt.get("fwdrev_over_fwd_time_f64")), _fmt(rt.get("fwdrev_over_fwd_time_f32")),
                    _fmt(rt.get("rev_over_fwd_time_f64")), _fmt(rt.get("rev_over_fwd_time_f32"))]
            lines.append("| " + " | ".join(row) + " |")
    # CPU use of the lfsim calls at each scene's largest N (small N are dominated by
    # single-threaded Python tracing of the IR).
    cpw = [r["cpu_per_wall"] for sc in report["scenes"] if sc.get("sizes")
           for k, r in list(sc["sizes"].values())[-1]["results"].items()
           if k.startswith("lfsim") and r.get("cpu_per_wall") is not None]
    if cpw:
        thr = report["environment"].get("drjit_threads")
        lines.append("")
        lines.append(f"At the largest N, lfsim calls used {min(cpw):.2f}-{max(cpw):.2f} CPU-s per wall-s "
                     f"(Dr.Jit threads: {thr}; NumPy and optiland run on one core)"
                     + ("; values well below the thread count mean other processes took CPU time"
                        if thr and min(cpw) < 0.75 * thr and max(report["settings"]["sizes"]) >= 1_000_000
                        else "") + ".")
    lines.append("")
    # First calls (compile) and agreement.
    lines.append("First call (s, includes IR tracing + kernel compile; compiled kernels in brackets), "
                 "at the first size:")
    lines.append("")
    lines.append("| scene | N | lfsim f64 fwd | lfsim f32 fwd | lfsim f64 fwd+rev | lfsim f32 fwd+rev |"
                 " kernels/call fwd, fwd+rev (f64) | peak RSS MB (largest N, f64 fwd+rev) |")
    lines.append("|---|---|---:|---:|---:|---:|---:|---:|")
    for sc in report["scenes"]:
        if "skipped" in sc or not sc["sizes"]:
            continue
        n0, sz = next(iter(sc["sizes"].items()))
        r = sz["results"]
        cells = []
        for key in ("lfsim_f64_fwd", "lfsim_f32_fwd", "lfsim_f64_fwdrev", "lfsim_f32_fwdrev"):
            fk = r[key]["first_call_kernels"]
            cells.append(f"{r[key]['first_call_s']:.2f} [{fk['compiled']}]")
        kpc = (f"{r['lfsim_f64_fwd']['kernels_per_call']['launched']}, "
               f"{r['lfsim_f64_fwdrev']['kernels_per_call']['launched']}")
        nl, szl = list(sc["sizes"].items())[-1]
        rss = szl["results"]["lfsim_f64_fwdrev"].get("peak_rss_mb")
        lines.append(f"| {Path(sc['scene']).stem} | {int(n0):.0e} | " + " | ".join(cells)
                     + f" | {kpc} | {_fmt(rss)} ({int(nl):.0e}) |")
    lines.append("")
    lines.append("Agreement (max |Δposition| at the image, mm, over rays OK in both; status mismatches):")
    lines.append("")
    lines.append("| scene | N | numpy vs lfsim f64 | status mism. | rays compared | lfsim f32 vs f64 |"
                 " optiland vs lfsim f64 |")
    lines.append("|---|---|---:|---:|---:|---:|---:|")
    for sc in report["scenes"]:
        if "skipped" in sc:
            continue
        for n, sz in sc["sizes"].items():
            a = sz["agreement"]
            npv = a.get("numpy_vs_lfsim_f64", {})
            f32 = a.get("lfsim_f32_vs_f64", {})
            opt = a.get("optiland_vs_lfsim_f64", {})

            def e(v):
                return "—" if v is None else f"{v:.2e}"

            lines.append(f"| {Path(sc['scene']).stem} | {int(n):.0e} | {e(npv.get('max_abs_dposition_mm'))} | "
                         f"{npv.get('status_mismatches', '—')} | {npv.get('rays_compared', '—')} | "
                         f"{e(f32.get('max_abs_dposition_mm'))} | {e(opt.get('max_abs_dposition_mm'))} |")
    for sc in report["scenes"]:
        for note in ([sc["skipped"]] if "skipped" in sc else sc.get("notes", [])):
            lines.append(f"\nNote ({Path(sc['scene']).stem}): {note}")
    return "\n".join(lines)


# -------------------------------------------------------------------- main
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=_sizes, default=[100_000, 1_000_000, 4_000_000],
                    help="comma-separated ray counts (default 1e5,1e6,4e6)")
    ap.add_argument("--scenes", nargs="+", default=DEFAULT_SCENES,
                    help="design files (relative paths: to the cwd, else to the repository root)")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="JSON output path")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats (best is reported)")
    ap.add_argument("--numpy-max-rays", type=_size, default=1_000_000,
                    help="time the NumPy baseline on at most this many rays (default 1e6)")
    ap.add_argument("--optiland-max-rays", type=_size, default=None,
                    help="time optiland on at most this many rays (default: all)")
    ap.add_argument("--optiland-glass", choices=("constant", "catalog"), default="constant",
                    help="optiland materials: lfsim's indices as constants (default) or optiland's catalog")
    ap.add_argument("--no-optiland", action="store_true", help="skip the optiland column")
    ap.add_argument("--threads", type=int, default=None, help="Dr.Jit worker threads (default: all cores)")
    ap.add_argument("--warm-cache", action="store_true",
                    help="use Dr.Jit's normal kernel cache (~/.drjit) instead of a fresh private one")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.repeats < 1:
        ap.error("--repeats must be >= 1")
    if args.threads is not None and args.threads < 1:
        ap.error("--threads must be >= 1")

    t_start = time.perf_counter()
    # Environment before Dr.Jit / numba are imported.
    private_home = None
    if not args.warm_cache:
        private_home = tempfile.mkdtemp(prefix="lfsim-bench-drjit-cache-")
        os.environ["HOME"] = private_home  # Dr.Jit keeps its kernel cache in $HOME/.drjit
    os.environ.setdefault("NUMBA_CACHE_DIR", "/tmp/numba_cache")
    sys.path.insert(0, str(Path(__file__).resolve().parent))

    def log(msg):
        print(msg, file=sys.stderr, flush=True)

    try:
        import drjit as dr

        import lfsim
        from lfsim import backend
        from lfsim.fileio import write_json

        if args.threads:
            backend.configure(threads=args.threads)
        device = backend.init()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            from importlib.metadata import version as _dist_version

            import optiland

            try:
                optiland_version = _dist_version("optiland")
            except Exception:
                optiland_version = getattr(optiland, "__version__", "installed")
        except ImportError as e:
            optiland_version = None
            args.optiland_unavailable = f"optiland not installed ({e}); column skipped"

        args.optiland_version = optiland_version
        report = {
            "benchmark": "trace_throughput",
            "settings": {"sizes": args.sizes, "repeats": args.repeats, "numpy_max_rays": args.numpy_max_rays,
                         "optiland_max_rays": args.optiland_max_rays, "optiland_glass": args.optiland_glass,
                         "seed": args.seed,
                         "drjit_kernel_cache": "~/.drjit (warm)" if args.warm_cache else "fresh private (cold)",
                         "timing": "warm-up call (first_call_s) then best of max(repeats, min(20, 1e6/N)) calls; "
                                   "lfsim calls end with "
                                   "dr.eval of p, d, status, opl (fwd) or of the gradient (fwd+rev) and "
                                   "dr.sync_thread(); includes Python-side IR construction",
                         "fwdrev_scalar": "dr.sum(mode='symbolic') over status==OK rays of x^2 + y^2 "
                                          "at the image surface; gradient w.r.t. the whole packed parameter array",
                         "ratios": "lfsim_f64_fwd_over_* are throughput ratios (speed-ups); "
                                   "fwdrev_over_fwd_time_* are time ratios; rev_over_fwd_time_* = (fwd+rev - fwd)/fwd"},
            "environment": {
                "python": platform.python_version(), "platform": platform.platform(),
                "cpu_count": os.cpu_count(), "numpy": np.__version__, "drjit": dr.__version__,
                "lfsim": lfsim.__version__, "optiland": optiland_version, "device": device,
                "drjit_threads": dr.thread_count() if device == "cpu" else None,
                "llvm": ".".join(map(str, dr.detail.llvm_version())) if device == "cpu" else None,
                "numpy_threads": 1, "git": _git_state(),
            },
            "scenes": [],
        }
        report["loadavg_start"] = _loadavg()
        if report["loadavg_start"] and report["loadavg_start"][0] > 0.5:
            log(f"WARNING: 1-min load average {report['loadavg_start'][0]:.2f} at start: other processes "
                "compete for the CPU and timings will be noisy")
        log(f"lfsim {lfsim.__version__} on {device} ({report['environment']['drjit_threads']} threads), "
            f"sizes {args.sizes}")
        for sc in args.scenes:
            p = Path(sc)
            if not p.exists() and not p.is_absolute() and (ROOT / p).exists():
                p = ROOT / p
            if not p.exists():
                note = f"{sc}: file not found, skipped"
                log(f"NOTE: {note}")
                report["scenes"].append({"scene": str(sc), "skipped": note})
                continue
            log(f"scene {p}")
            t_sc = time.perf_counter()
            res = bench_scene(p, args, log)
            res["wall_s"] = time.perf_counter() - t_sc
            report["scenes"].append(res)
        _rss_mb()
        report["loadavg_end"] = _loadavg()
        report["max_rss_mb_process"] = _MAX_RSS_MB[0]  # max of the per-case peaks (VmHWM)
        report["total_wall_s"] = time.perf_counter() - t_start
        table = markdown(report)
        report["markdown"] = table
        print(table)
        print(f"\nTotal run time {report['total_wall_s']:.1f} s; max RSS {report['max_rss_mb_process']:.0f} MB")
        write_json(args.out, _finite(report))
        print(f"wrote {args.out}")
    finally:
        if private_home:
            shutil.rmtree(private_home, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
