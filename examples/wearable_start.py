"""A wearable start from a bench design's prism, scaled, with a four-singlet relay fitted to it.

The wearable start ``scenes/ini_wearable.toml`` was laid out with the bench prism scaled by
0.6. This script builds such starts for any scale and any bench prism, so that the scale is
a thing one can try: it takes

* ``--prism``: an InI design whose prism (``S1`` … ``S4``) and viewing window ``VW`` are used,
  e.g. the bench design re-optimized at a longer eye relief by
  ``examples/eye_relief_sweep.py`` (``DIR/er_25/opt/er_25.toml``);
* ``--base``: the wearable design whose lenslet array, aperture array ``AA``, four singlets
  ``R1a`` … ``R4b``, tunable lens, ``[ini]`` and ``[optimize]`` sections are kept
  (default ``scenes/ini_wearable.toml``);
* ``--scale s``: the prism and window are scaled by ``s`` about the point where the prism
  design's axis meets the plane of ``S1``'s vertex (positions, radii, XY coefficients and
  normalization radii, aspheric coefficients, apertures), so the eye relief becomes ``s``
  times the prism design's.

The relay is then fitted paraxially so that the whole display path keeps the prism
design's first order **exactly** (CDP at every state, EI pitch, angular pixel, FOV, window):
with ``M_k`` the prism design's 4 × 4 first-order map of CDP state ``k`` from the lenslet
array's back plane to the window, ``P`` its prism part (the plane of ``S1``'s vertex → the
window) and ``D = diag(s, s, 1, 1)``, the new relay must map that back plane to the scaled
``S1`` plane by ``(D P D⁻¹)⁻¹ M_k``. A coaxial relay has one 2 × 2 matrix for both
meridians, so the target is the mean of the x and y meridians' (the prism is anamorphic; the
optimizer's freeform terms take up the rest). The search is ``examples/relay_petzval.py``'s:
four singlets in ``--glasses``, six air gaps and the tunable power, the target matrix at 1 D
and the direction of its derivative in the tunable power (so the states map one to one),
every package rule (clear diameter, tunable footprint ≤ ``--tunable-footprint``, glass and
air ≥ 1 mm at centre and edge, slope, ``--back`` mm from the last lens to ``S1``), the relay's
length such that the track is at most ``--track``, colour no more than ``--base``'s relay,
and the least third-order field curvature. Finally each prism face's clear aperture is set to
a rectangle about its footprint (the ``package`` ray set) plus ``--margin``, as the 0.6 start
did for ``S1``. Run::

    python examples/wearable_start.py --prism DIR/er_25/opt/er_25.toml --scale 0.732 --out OUT

It prints the relay found and the new start's ``package`` and first-order figures, and writes
``OUT/ini_wearable_s<scale>.toml`` (ready for ``lfsim optimize``) and ``OUT/wearable_start.json``.
"""

from __future__ import annotations

import copy
import math
import sys
import tomllib
from pathlib import Path

import numpy as np
import tomli_w
from relay_petzval import Rules, Search, bundle, dispersion, parse_glasses, read_relay, search, seidel, write_variant

from lfsim.cli import OneLineParser
from lfsim.fileio import write_json, write_text
from lfsim.optics.materials import lookup

ROOT = Path(__file__).resolve().parents[1]
PRISM = ("S1", "S2", "S3", "S4")


def _prop(d: float) -> np.ndarray:
    """4 × 4 free-space map of a state (x, y, tan_x, tan_y) over ``d`` mm."""
    P = np.eye(4)
    P[0, 2] = P[1, 3] = d
    return P


def _meridians(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return A[np.ix_([0, 2], [0, 2])], A[np.ix_([1, 3], [1, 3])]


def prism_maps(design):
    """First-order maps of the prism ``design`` (a :class:`lfsim.design.Design`):
    ``(M, P, z_back, z_s1, track_rest, phis, model)``.
    ``M`` (K, 4, 4): lenslet array's back plane → window, per CDP state; ``P`` (4, 4): the plane
    of S1's vertex (z = ``z_s1``) → window; ``track_rest``: the track from that plane on."""
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    model = IniModel(design)
    names = [s.name for s in model.system.surfaces]
    i1 = names.index("S1")
    K = len(model.depths)
    blocks = np.stack([model.values(k) for k in range(K)])
    _, M = model._group_maps(blocks)
    frames = model.tracer.frames_numpy(model.tracer.params(values=model.values0))
    z_s1 = float(frames[i1][1][2])
    _, R = model._linearize(blocks, np.zeros(4), model.z_mla_back, model.spec.mla_surfaces[-1] + 1, i1 - 1,
                            (np.eye(3), np.array([0.0, 0.0, z_s1])), False)
    Ps = [M[k] @ np.linalg.inv(R[k]) for k in range(K)]
    spread = max(float(np.max(np.abs(p - Ps[0]))) for p in Ps)
    if spread > 1e-8 * max(1.0, float(np.max(np.abs(Ps[0])))):
        raise ValueError(f"{model.file}: the map S1 → VW differs between CDP states by {spread:.3g}: "
                         f"the tunable lens must lie before S1")
    track = float(package(model, solids=False)["track_mm"])
    rest = track - (z_s1 + model.g)  # the display lies at z = −g
    phis = np.array(model.tl_power, dtype=np.float64)  # mm⁻¹
    return M, Ps[0], model.z_mla_back, z_s1, rest, phis, model


def relay_target(M, P, phis, s: float, dz_aa: float, k1: int):
    """The relay's target: ``(M0, a0, b0)`` for :class:`Search`, in the AA plane's (y, ν), mean of
    the two meridians, and the per-meridian targets at 1 D (for the report)."""
    D = np.diag([s, s, 1.0, 1.0])
    Psc = D @ P @ np.linalg.inv(D)
    T = [np.linalg.inv(Psc) @ Mk @ _prop(-dz_aa) for Mk in M]
    tx, ty = _meridians(T[k1])
    M0 = 0.5 * (tx + ty)
    M0 = M0 / math.sqrt(np.linalg.det(M0))
    dT = [0.5 * sum(_meridians(T[0] - T[-1]))]
    u, sv, vt = np.linalg.svd(dT[0])
    # T(φ) = T(φ₁) − (φ − φ₁)·b0·a0ᵀ (a thin tunable lens): b0·a0ᵀ = −(T₀ − T_last)/(φ₀ − φ_last)
    return M0, vt[0].copy(), -sv[0] * u[:, 0] / (phis[0] - phis[-1]), (tx, ty)


def scale_prism(raw_prism: dict, s: float, z_s1: float, z_new: float) -> list[dict]:
    """The prism design's S1 … S4 and VW tables, scaled by ``s`` about (0, 0, ``z_s1``) and moved
    so that point lies at (0, 0, ``z_new``)."""
    out = []
    names = [x.get("name") for x in raw_prism["surfaces"]]
    vw = raw_prism["ini"]["viewing_window"]
    for name in (*PRISM, vw):
        t = copy.deepcopy(raw_prism["surfaces"][names.index(name)])
        g = [float(v) for v in t["global_position"]]
        t["global_position"] = [s * g[0], s * g[1], z_new + s * (g[2] - z_s1)]
        if "radius" in t:
            t["radius"] = float(t["radius"]) * s
        if "curvature" in t:
            t["curvature"] = float(t["curvature"]) / s
        if "norm_radius" in t:
            t["norm_radius"] = float(t["norm_radius"]) * s
        if "xy" in t:
            t["xy"] = {k: float(v) * s for k, v in t["xy"].items()}
        if "asphere" in t:
            t["asphere"] = {k: float(v) * s ** (1 - int(k[1:])) for k, v in t["asphere"].items()}
        for key in ("semi_diameter", "thickness"):
            if key in t:
                t[key] = float(t[key]) * s
        ap = t.get("aperture")
        if ap is not None:
            for key in ("radius", "half_width", "decenter"):
                if key in ap:
                    ap[key] = [float(v) * s for v in ap[key]] if isinstance(ap[key], list) else float(ap[key]) * s
        t["comment"] = (t.get("comment", "") + f" (scaled by {s:g})").strip()
        out.append(t)
    return out


def trim_apertures(design, margin: float) -> dict:
    """Each prism face's rectangle about its footprint (the package ray set's local hits in
    ``design``) plus ``margin``: ``{name: {"type", "half_width", "decenter"}}``."""
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import ray_set
    from lfsim.ini.subsystems import trace_rays_jacobian

    model = IniModel(design)
    names = [x.name for x in model.system.surfaces]
    idx = [names.index(n) for n in PRISM]
    s, m, n, rho, k, _ = ray_set(model)
    J = trace_rays_jacobian(model, s, m, n, rho, k, [], record=idx, derivatives=False)
    ok = J.status == 0
    out = {}
    for c, name in enumerate(PRISM):
        h = J.surf[ok, c]
        lo, hi = h.min(axis=0), h.max(axis=0)
        hx, hy, dy = 0.5 * (hi[0] - lo[0]) + margin, 0.5 * (hi[1] - lo[1]) + margin, 0.5 * (hi[1] + lo[1])
        surf = model.system.surfaces[idx[c]]
        if surf.curvature != 0.0:  # a sphere's surface ends at |R| from its axis: corners at 98 % of it
            reach = 0.98 / abs(surf.curvature)
            if math.hypot(hx, abs(dy) + hy) > reach:  # shrink both half-widths by f: |(f·hx, |dy| + f·hy)| = reach
                a, b, cc = hx * hx + hy * hy, 2.0 * abs(dy) * hy, dy * dy - reach * reach
                f = (-b + math.sqrt(b * b - 4.0 * a * cc)) / (2.0 * a)
                hx, hy = f * hx, f * hy
        out[name] = {"type": "rectangular", "half_width": [float(hx), float(hy)], "decenter": [0.0, float(dy)]}
    return out, int(np.sum(~ok)), int(len(ok))


def main(argv=None) -> int:
    ap = OneLineParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--prism", required=True, help="InI design whose prism S1..S4 and window are scaled")
    ap.add_argument("--base", default=str(ROOT / "scenes" / "ini_wearable.toml"),
                    help="wearable design whose lenslets, relay lenses, [ini] and [optimize] are kept "
                         "(default: %(default)s)")
    ap.add_argument("--scale", type=float, required=True, help="scale of the prism and window")
    ap.add_argument("--out", required=True)
    ap.add_argument("--glasses", default="N-LAK22,N-LAK22,N-LAK22,N-LAK22", help="four relay glasses")
    ap.add_argument("--track", type=float, default=149.7, help="largest track, mm (default: %(default)s)")
    ap.add_argument("--back", type=float, default=8.0,
                    help="least distance from the last relay lens to S1's vertex plane, mm (default: %(default)s)")
    ap.add_argument("--tunable-footprint", type=float, default=9.7,
                    help="largest paraxial footprint on the tunable lens, mm (default: %(default)s)")
    ap.add_argument("--tunable-range", default="8.3,20",
                    help="tunable-lens powers the fitted relay may use at the CDP states, diopters (default: the "
                         "EL-10-30-C's range, %(default)s)")
    ap.add_argument("--clear-diameter", type=float, default=23.2, help="largest lens clear diameter, mm")
    ap.add_argument("--colour-max", type=float, default=1.0,
                    help="largest first-order colour, as a multiple of --base's relay's (default: %(default)s)")
    ap.add_argument("--margin", type=float, default=1.0, help="prism apertures beyond the footprint, mm")
    ap.add_argument("--pupil-weight", type=float, default=0.0,
                    help="weight of the relay's pupil spherical aberration (third order, the corner chief ray's "
                         "S_I, in units of --base's relay's) beside the field curvature (default: %(default)s)")
    ap.add_argument("--starts", type=int, default=12)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    if not (0.1 <= args.scale <= 2.0):
        ap.error(f"--scale {args.scale}: between 0.1 and 2")
    try:
        t_lo, t_hi = (float(v) for v in args.tunable_range.split(","))
    except ValueError:
        ap.error(f"--tunable-range {args.tunable_range!r}: two numbers of diopters, comma separated")
    if not t_lo < t_hi:
        ap.error(f"--tunable-range {args.tunable_range!r}: the first below the second")
    glasses = parse_glasses(ap, args.glasses)
    from lfsim.design.design import load
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    prism_path, base_path, s = Path(args.prism), Path(args.base), float(args.scale)
    try:
        raw_p = tomllib.loads(prism_path.read_text())
        raw_b = tomllib.loads(base_path.read_text())
        M, P, z_back_p, z_s1, rest, phis_p, model_p = prism_maps(load(prism_path))
        rays, marginal = bundle(prism_path, first_face=_first_relay_face(raw_p))
        base = IniModel(load(base_path))
        lam = float(base.lam)
        ref, phis_ref = read_relay(raw_b, lam, [base.state(k).tunable_power_diopters for k in range(len(base.depths))])
    except (OSError, tomllib.TOMLDecodeError, ValueError, KeyError) as e:
        print(f"wearable_start.py: error: {e}", file=sys.stderr)
        return 2
    names_b = [x.get("name") for x in raw_b["surfaces"]]
    frames_b = base.tracer.frames_numpy(base.tracer.params(values=base.values0))
    z_aa = float(frames_b[names_b.index("AA")][1][2])
    z_disp = -base.g
    if abs(base.g - model_p.g) > 1e-9 or abs(z_back_p - base.z_mla_back) > 1e-9:
        print(f"wearable_start.py: error: {base_path}: its lenslet array differs from {prism_path}'s "
              f"(display gap {base.g:g} / {model_p.g:g} mm)", file=sys.stderr)
        return 2
    k1 = int(np.argmin(np.abs(np.asarray(base.depths) - 1.0)))
    M0, a0, b0, (tx, ty) = relay_target(M, P, phis_p, s, z_aa - base.z_mla_back, k1)
    max_len = args.track - (z_aa - z_disp) - s * rest
    rules = Rules(clear_diameter=args.clear_diameter, max_length=max_len, colour_max=args.colour_max,
                  min_back=args.back, tunable_range=(t_lo * 1e-3, t_hi * 1e-3))
    S = Search(ref, phis_ref, rays, marginal, rules, k1=k1)
    # the prism design's first order in place of the base relay's
    S.phis = phis_p
    S.M0, S.a0, S.b0 = M0, a0, b0
    S.tun0 = 0.5 * args.tunable_footprint
    h = float(np.max(np.hypot(rays[:, 0], rays[:, 1])))
    S.marginal, S.chief = tuple(marginal[k1]), (h, -a0[0] * h / a0[1])
    S.seidel0 = seidel(ref, phis_ref[k1], S.marginal, S.chief)
    n = np.array([float(lookup(g).index(lam)) for g in glasses])
    dn = np.array([dispersion(g) for g in glasses])
    print(f"{prism_path.name}: prism part of the track {rest:.2f} mm (scaled: {s * rest:.2f}); relay length "
          f"at most {max_len:.2f} mm (base relay: {ref.length:.2f} mm)")
    print(f"target relay matrix at 1 D (AA plane -> S1 plane): x {np.round(tx, 5).tolist()}, "
          f"y {np.round(ty, 5).tolist()}")
    if args.pupil_weight > 0:
        fc_only, w = S.field_curvature, float(args.pupil_weight)
        p0 = seidel(ref, phis_ref[k1], S.chief, S.marginal)[0]

        def objective(x, n_new):
            p = seidel(S._relay(x, n_new), x[18], S.chief, S.marginal)[0]
            return fc_only(x, n_new) + w * (p / p0) ** 2
        S.field_curvature = objective
    x0 = np.concatenate([ref.pack(), [phis_ref[k1]]])
    warm = [x0]
    S.start = _starts(x0)  # random starts about the base relay (its own first order)
    found = search(S, glasses, lam, args.starts, args.seed, warm=warm)
    if found is None:
        print(f"wearable_start.py: error: no feasible relay in {args.starts + 1} SLSQP runs "
              f"(try a longer --track, a smaller --back or another --scale)", file=sys.stderr)
        return 2
    x, fc, nf, origin = found
    r = S._relay(x, n, dn)
    face, tun = S.semi_diameters(x, n)
    powers, _ = S.state_powers(x, n)
    semi = S.lens_semi_diameters(face)
    sums = seidel(r, x[18], S.marginal, S.chief)
    pupil = seidel(r, x[18], S.chief, S.marginal)[0] / seidel(ref, phis_ref[k1], S.chief, S.marginal)[0]
    fc3 = Search.field_curvature(S, x, n)
    print(f"relay: field curvature {fc3:.3f} (the base relay's S_IV² = 1), pupil spherical aberration {pupil:.3f} "
          f"of the base relay's, length {r.length:.2f} mm, lens powers "
          f"{', '.join(f'{v:.1f}' for v in (r.n - 1.0) * (r.c1 - r.c2) * 1e3)} D, tunable "
          f"{', '.join(f'{p * 1e3:.2f}' for p in powers)} D, footprint {2 * tun:.2f} mm; {nf} feasible runs")

    raw = write_variant(raw_b, r, glasses, powers, ref.length, semi=semi)
    # the scaled prism: S1's plane at the relay's end
    z_end = z_aa + r.length
    new = scale_prism(raw_p, s, z_s1, z_end)
    names = [t.get("name") for t in raw["surfaces"]]
    for t in new:
        raw["surfaces"][names.index(t["name"])] = t
    raw["ini"]["viewing_window"] = raw_p["ini"]["viewing_window"]
    out = Path(args.out)
    tag = f"{s:g}".replace(".", "p")
    dst = out / f"ini_wearable_s{tag}.toml"
    from lfsim.design import Design

    aps, failed, total = trim_apertures(Design.from_dict(raw, str(dst)), args.margin)
    out.mkdir(parents=True, exist_ok=True)
    names = [t.get("name") for t in raw["surfaces"]]
    for name, a in aps.items():
        raw["surfaces"][names.index(name)]["aperture"] = a
    raw["name"] = f"Wearable InI-HMD start: {prism_path.stem}'s prism scaled by {s:g}, four-singlet relay fitted"
    write_text(dst, _header(args, prism_path, base_path) + tomli_w.dumps(raw))
    model = IniModel(load(dst))
    pk = package(model)
    st = model.state(k1)
    doc = {"prism": str(prism_path), "base": str(base_path), "scale": s, "design": str(dst),
           "relay": {"objective": float(fc), "field_curvature": float(fc3), "pupil_spherical_ratio": float(pupil),
                     "length_mm": r.length, "gaps_mm": r.gaps.tolist(),
                     "c1": r.c1.tolist(), "c2": r.c2.tolist(), "thickness_mm": r.t.tolist(),
                     "semi_diameter_mm": semi.tolist(), "glasses": list(glasses), "seidel": sums.tolist(),
                     "tunable_power_diopters": (powers * 1e3).tolist(), "tunable_footprint_mm": 2 * tun,
                     "best_start": origin, "feasible_runs": int(nf)},
           "rays_failed_before_trim": failed, "rays_traced": total,
           "package": pk, "first_order_1d": st.as_dict(),
           "prism_design_first_order_1d": model_p.state(k1).as_dict()}
    write_json(out / "wearable_start.json", doc)
    print(f"start: track {pk['track_mm']:.2f} mm, box {' x '.join(f'{v:.1f}' for v in pk['bounding_box_mm'])} mm, "
          f"prism {' x '.join(f'{v:.1f}' for v in pk['prism_box_mm'])} mm, eye relief {pk['eye_relief_mm']:.2f} mm, "
          f"glass edge {pk['min_edge_thickness_mm']:.2f} mm, tunable footprint {pk['tunable_footprint_mm']:.2f} mm, "
          f"{pk['rays_failed']} of {pk['rays_traced']} package rays lost")
    p0 = model_p.state(k1)
    print(f"first order at 1 D: FOV {st.fov_deg[0]:.2f} x {st.fov_deg[1]:.2f} deg (prism design "
          f"{p0.fov_deg[0]:.2f} x {p0.fov_deg[1]:.2f}), pixel {st.pixel_arcmin[0]:.3f} x {st.pixel_arcmin[1]:.3f}', "
          f"CDP {st.cdp_diopters_x:.3f} / {st.cdp_diopters_y:.3f} D")
    print(f"wrote {dst}, {out / 'wearable_start.json'}")
    return 0


def _first_relay_face(raw: dict) -> str:
    names = [x.get("name") for x in raw["surfaces"]]
    return names[names.index("AA") + 1]


def _starts(x0):
    def start(n_new, rng=None, spread=0.0):
        x = x0.copy()
        if rng is not None and spread > 0:
            x[6:14] += rng.normal(0.0, spread * 0.01, 8)
            x[:6] *= np.exp(rng.normal(0.0, spread * 0.15, 6))
        return x
    return start


def _header(args, prism: Path, base: Path) -> str:
    return (f"# Made by: python examples/wearable_start.py --prism {prism} --base {base} --scale {args.scale:g} "
            f"--glasses {args.glasses} --track {args.track:g} --back {args.back:g} --margin {args.margin:g} "
            f"--tunable-range {args.tunable_range} --pupil-weight {args.pupil_weight:g}\n")


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
