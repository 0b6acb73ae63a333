"""Synthetic aberrations: GD (Eq. 11) and PA (Eq. 12) against injected distortion
and pupil aberration, in the spirit of Figs. 4 and 5 of the design method.

System (built in memory from ``scenes/ini_ideal.toml``): an ideal InI-HMD with
11 x 11 paraxial lenslets of 1 mm pitch (f_MLA = 3.5 mm), a tunable lens TL in
contact with an ideal eyepiece EP, the viewing window VW at the eyepiece's
back focal point and the CDP at 1 D. The eyepiece focal length and the display
gap are solved so that the 11 x 11 virtual EI centres span 40 deg x 40 deg
(outer centres at +-20 deg on each axis) and the footprint is d_v = 1 mm.

Aberrations are injected with zero-thickness plates (index 1.5) whose only
terms vanish to second order at the axis (r^4, x^2 y) or are linear (x), so
the first-order model -- lfsim's paraxial reference -- is unchanged (checked):

* distortion: a *pair* of identical XY/asphere plates facing each other 20 mm
  apart, straddling the intermediate CDP (l behind the MLA). The first plate
  deflects a ray by (n-1) grad S, the second undoes it, so the pair displaces
  rays laterally by about e (n-1) grad S without changing their directions:
  the intermediate image is remapped (distortion) while the chief rays still
  meet at the VW centre. S = A4 r^4 gives barrel (A4 < 0) or pincushion
  (A4 > 0); S = c (x/R)^2 (y/R) gives keystone (with its companion smile).
  A remapping with local magnification J also scales each bundle's angular
  spread by J^-1 (Lagrange invariant), so footprints change size a little:
  the PA reported beside GD in the distortion sweep.
* pupil spherical aberration: one A4 r^4 plate in contact with the eyepiece
  (the eyepiece group carries the aberration, the lenslets stay ideal, as in
  the paper). It acts on the bundle of the on-axis EI's centre pixel, which
  fills a d_v-wide disc there; only that field is evaluated (Fig. 5).
* pupil tilt: one linear plate (a thin prism) at the intermediate CDP, where
  the rays of each pixel meet: it deflects every bundle by the same angle, so
  the footprints move on the VW and no image point moves (GD stays ~0).

Measured quantities (from traced rays, independent of the injected
coefficients):

* distortion % = 100 (|v| - |v_par|)/|v_par| of the centre-field chief ray's
  visual tangent, mean of the four corner EIs (the full-field corner of the
  11 x 11 grid); also at the four edge-midpoint EIs. Real v from an
  independent trace (``Design.trace``: display EI centre -> lenslet centre ->
  VW, TL at the closed-form 1 D power), v_par from the closed-form Eq. (9)
  (``lfsim.ini.first_order``) -- neither uses lfsim's InI pipeline.
* keystone % = 100 (w_top - w_bottom)/(w_top + w_bottom), w the horizontal
  visual-tangent width between the corner EIs of the top/bottom row.
* pupil SA (waves PV) = W040 of the wavefront the plate adds to the on-axis
  centre-pixel bundle, fitted (W = W020 rho^2 + W040 rho^4 + tilts) to the
  traced ray-slope changes at the eyepiece, rho normalized to the paraxial
  footprint radius there (the circle through the four marginal rays of
  Eq. 12): PV of the pure rho^4 term over that circle.
* pupil tilt (deg) = atan(mean VW displacement of the four marginal rays /
  z_xp), z_xp = eyepiece -> VW distance: the rotation about the eyepiece of
  the chief-ray bundle that converges on the VW.

GD and PA are lfsim's own: ``lfsim.analysis.ini_analysis.evaluate``. Its
paraxial reference is the traced design's own first-order model, linearized
about the design's real axis ray, with the EI layout re-solved on it: that is
the nominal model for every injection here except the tilt, whose deflection
of the axis ray it absorbs (PA ~ 4e-4 at 1 deg). PA and GD are therefore also
computed with lfsim's metric functions against the nominal (zero-injection)
paraxial model -- the paper's reference (Eq. 9, x_v0 = y_v0 = 0) -- and that is
what the tilt rows report.

Run::

    .venv/bin/python examples/synthetic_aberrations.py --out docs/img
"""

from __future__ import annotations

import copy
import math
import time
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

import lfsim
from lfsim.analysis.ini_analysis import evaluate, summarize
from lfsim.cli import OneLineParser
from lfsim.fileio import save_figure, write_json
from lfsim.ini.first_order import ini_first_order
from lfsim.ini.model import IniModel
from lfsim.ini.subsystems import sample, trace
from lfsim.metrics import distortion, footprint, pupil

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "ini_ideal.toml"

# ------------------------------------------------------------------ the system
P_MLA = 1.0  # lenslet pitch (mm)
F_MLA = 3.5  # lenslet focal length (mm)
M_LENS = N_LENS = 11  # lenslets = sampled EI centres (the paper's 11 x 11 grid)
CDP_D = 1.0  # CDP depth (diopters)
HALF_FOV_DEG = 20.0  # outer EI centres at +-20 deg on each axis: 40 x 40 deg
D_V_TARGET = 1.0  # footprint width on the VW (mm), as in Fig. 5
N_PLATE = 1.5  # index of the aberration plates
PAIR_GAP = 20.0  # distance between the two faces of the distortion pair (mm)
NORM_R = 5.0  # norm_radius of the XY terms (mm)
CENTER = (M_LENS // 2, N_LENS // 2)  # the on-axis lenslet (0-based)

#: The paper's numbers (Sections 4 and 5).
PAPER = {
    "gd_max_deg": {"barrel 1%": 0.36, "barrel 5%": 1.78},
    "pa": {"pupil SA 0.25 waves PV": 0.059, "pupil SA 1 waves PV": 0.23},
}

ZERO = {"radial_A4": 0.0, "keystone": 0.0, "pupil_sa_A4": 0.0, "pupil_tilt": 0.0}


@dataclass
class Geometry:
    f_ep: float  # eyepiece focal length = EP -> VW distance z_xp = intermediate CDP -> EP (mm)
    l: float  # noqa: E741 - MLA -> intermediate CDP (mm)
    g: float  # display -> MLA gap (mm)

    @property
    def tl_diopters(self) -> float:
        """Closed-form tunable-lens power for the CDP: the thin TL+EP pair images the
        intermediate CDP (f_ep in front) to 1000/D - z_xp in front of the eyepiece."""
        return -1000.0 / (1000.0 / CDP_D - self.f_ep)


def design_dict(geom: Geometry, inj: dict | None = None) -> dict:
    """The design as a dict (the schema of ``docs/design-files.md``), plates included.

    Every plate is always present (zero coefficients when not injected), so all
    cases share one surface table: zero injection is the ideal design exactly
    (a zero-thickness flat plate refracts in and straight back out).
    """
    inj = {**ZERO, **(inj or {})}
    data = tomllib.loads(SCENE.read_text())
    data["name"] = "Synthetic-aberration InI-HMD (40 x 40 deg, CDP 1 D)"
    data["arrays"]["mla"].update(m=M_LENS, n=N_LENS, pitch=[P_MLA, P_MLA])
    data["object"]["distance"] = geom.g
    data["ini"]["cdp_diopters"] = [CDP_D]
    data["ini"]["analysis"] = {"pupil": 2, "mtf_grid": 8}  # GD/PA only: keep the MTF rules small
    mla, tl, ep, vw = (copy.deepcopy(s) for s in data["surfaces"])
    e, f = PAIR_GAP, geom.f_ep
    a4, kst = float(inj["radial_A4"]), float(inj["keystone"])
    mla["focal_length"] = F_MLA
    mla["thickness"] = geom.l - 0.5 * e

    def plate_flat(name, material, thickness):
        return {"name": name, "radius": math.inf, "material": material, "thickness": thickness, "virtual": True}

    pair_terms = {"asphere": {"A4": a4}, "xy": {"x2y1": kst}, "norm_radius": NORM_R}
    surfaces = [
        mla,
        # distortion pair, face A (glass -> air, sag S) ...
        plate_flat("DA_in", N_PLATE, 0.0),
        {"name": "DA", "comment": "distortion pair, first face", **copy.deepcopy(pair_terms),
         "material": "air", "thickness": 0.5 * e},
        # ... pupil-tilt prism at the intermediate CDP ...
        plate_flat("PT_in", N_PLATE, 0.0),
        {"name": "PT", "comment": "pupil tilt (thin prism) at the intermediate CDP",
         "xy": {"x1y0": float(inj["pupil_tilt"])}, "material": "air", "thickness": 0.5 * e},
        # ... face B (air -> glass, the same sag S): undoes A's deflection.
        {"name": "DB", "comment": "distortion pair, second face", **copy.deepcopy(pair_terms),
         "material": N_PLATE, "thickness": 0.0},
        plate_flat("DB_out", "air", f - 0.5 * e),
        # pupil spherical aberration, in contact with the eyepiece group
        plate_flat("SA_in", N_PLATE, 0.0),
        {"name": "SA", "comment": "pupil spherical aberration plate at the eyepiece",
         "asphere": {"A4": float(inj["pupil_sa_A4"])}, "material": "air", "thickness": 0.0},
    ]
    tl["focal_length"] = 1000.0 / geom.tl_diopters  # the closed-form 1 D power (IniModel re-solves it)
    tl["thickness"] = 0.0
    ep["focal_length"] = f
    ep["thickness"] = f
    # Zero-thickness plates are thin-element idealizations: a sagged face and its
    # neighbours at one vertex are crossed "backwards" where the sag is negative.
    for sf in surfaces[1:] + [tl]:
        sf["virtual"] = True
    data["surfaces"] = surfaces + [tl, ep, vw]
    return data


def build(geom: Geometry, inj: dict | None = None):
    """(Design, IniModel) of one injection."""
    d = lfsim.Design.from_dict(design_dict(geom, inj))
    return d, IniModel(d)


def solve_geometry(tol: float = 1e-11, max_iter: int = 60) -> Geometry:
    """f_ep and g such that the EI-centre step is tan(20 deg)/5 and d_v = 1 mm at the CDP
    (lfsim's own first-order model; fixed point: step ~ 1/f_ep, d_v ~ 1/l)."""
    target = math.tan(math.radians(HALF_FOV_DEG)) / ((M_LENS - 1) / 2)
    f, l = 13.37, 13.55
    for _ in range(max_iter):
        geom = Geometry(f, l, 1.0 / (1.0 / F_MLA - 1.0 / l))
        st = build(geom)[1].state(0)
        step = math.tan(math.radians(st.delta_theta_eic_deg[0]))
        ef, el = step / target, st.d_v[0] / D_V_TARGET
        if abs(ef - 1) < tol and abs(el - 1) < tol:
            return geom
        f, l = f * ef, l * el
    raise RuntimeError(f"geometry did not converge: {ef - 1:.3g}, {el - 1:.3g}")


def closed_form(geom: Geometry):
    """Eqs. (1)-(10) for the thin TL+EP pair (``lfsim.ini.first_order``), the paraxial
    reference of the independent measurement."""
    F = 1.0 / (1.0 / geom.f_ep + geom.tl_diopters / 1000.0)
    return ini_first_order(P_MLA, geom.g, F, geom.f_ep, M_LENS, N_LENS, f_mla=F_MLA, z_ic=geom.f_ep)


def all_lenslets() -> list[tuple[int, int]]:
    """0-based (m, n), m fastest: reshape per-lenslet arrays to (N, M)."""
    return [(i, j) for j in range(N_LENS) for i in range(M_LENS)]


# -------------------------------------------------------- independent measure
def chief_rays(design, geom: Geometry, fo) -> tuple[np.ndarray, np.ndarray]:
    """Visual tangents (N, M, 2) of the EI-centre chief rays: real (independent
    ``Design.trace``) and paraxial (closed-form Eq. 9). Visual = direction of the
    virtual point seen from the VW centre = -(retinal tangent t - h D)."""
    o, dirs, vpar = [], [], []
    for j in range(N_LENS):
        for i in range(M_LENS):
            s = np.array(fo.ei_center(i + 1, j + 1))
            c = np.array(fo.lenslet_center(i + 1, j + 1))
            o.append([s[0], s[1], -geom.g])
            dirs.append([c[0] - s[0], c[1] - s[1], geom.g])
            vpar.append(np.array(fo.virtual_ei_center(i + 1, j + 1)) / fo.z_cdp)
    lens = np.array(all_lenslets(), dtype=np.int64)
    r = design.trace(np.array(o), np.array(dirs), lenslet=lens)
    if np.any(r.status != 0):
        raise RuntimeError(f"chief rays failed: {np.unique(r.status)}")
    t = r.directions[:, :2] / r.directions[:, 2:3]
    vis = -(t - r.positions[:, :2] * (CDP_D / 1000.0))
    return vis.reshape(N_LENS, M_LENS, 2), np.array(vpar).reshape(N_LENS, M_LENS, 2)


def distortion_measures(v: np.ndarray, vp: np.ndarray) -> dict:
    """Distortion % at the corner and edge EIs, keystone %, from visual tangents (N, M, 2)."""
    rad, radp = np.hypot(v[..., 0], v[..., 1]), np.hypot(vp[..., 0], vp[..., 1])
    cj, ci = N_LENS // 2, M_LENS // 2
    corners = [(0, 0), (0, -1), (-1, 0), (-1, -1)]
    edges = [(0, ci), (-1, ci), (cj, 0), (cj, -1)]
    rel = lambda idx: float(np.mean([(rad[a] - radp[a]) / radp[a] for a in idx]))  # noqa: E731
    w_top = v[-1, -1, 0] - v[-1, 0, 0]
    w_bot = v[0, -1, 0] - v[0, 0, 0]
    return {"corner_pct": 100 * rel(corners), "edge_pct": 100 * rel(edges),
            "keystone_pct": float(100 * (w_top - w_bot) / (w_top + w_bot)),
            "gd_indep_max_deg": float(np.max(distortion.gd_deg(v, vp)))}


def measure_distortion(geom: Geometry, inj: dict, fo=None) -> dict:
    fo = fo or closed_form(geom)
    d = lfsim.Design.from_dict(design_dict(geom, inj))
    return distortion_measures(*chief_rays(d, geom, fo))


# ------------------------------------------------------------------ lfsim's GD/PA
def lfsim_metrics(model: IniModel, lenslets, nominal: IniModel | None = None) -> dict:
    """lfsim's GD and PA of the EI-centre fields of ``lenslets`` (CDP state 0).

    With ``nominal``, the same real rays (from the nominal display layout) are
    also measured against the nominal design's paraxial model: the paper's
    reference (Eq. 9 and x_v0 = y_v0 = 0), which ``evaluate`` replaces by the
    traced design's own first-order model.
    """
    ref = nominal or model
    subs = sample(ref, lenslets=lenslets, depths=[0], fields=np.zeros((1, 2)))
    res = evaluate(model, subs)
    s = summarize(res)["summary"]
    out = {"gd": res["gd"], "pa": res["pa"][:, 0], "gd_max_deg": s["gd_max_deg"],
           "gd_mean_deg": s["gd_mean_deg"], "pa_max": s["pa_max"], "pa_mean": s["pa_mean"],
           "res": res}
    if nominal is not None:
        sets, D = res["sets"], nominal.depths[0]
        mk = sets.slices["marginal"]
        S, R = len(subs), len(sets.rho)
        par = nominal.paraxial_vw(0, np.broadcast_to(subs.display[:, 0, None, :], (S, R, 2)),
                                  np.broadcast_to(subs.center[:, None, :], (S, R, 2)),
                                  np.broadcast_to(sets.rho[None], (S, R, 2)))[:, None]  # (S, 1, R, 4)
        r_par = par[..., 2:4] - par[..., 0:2] * (D / 1000.0)
        ch = sets.slices["chief"].start
        gd = distortion.gd_deg(res["r"][:, 0, ch], r_par[:, 0, ch])
        pa = footprint.pa(res["bundle"].pos[:, :, mk], par[:, :, mk, 0:2], np.mean(nominal.state(0).d_v))[:, 0]
        out.update(gd_nom=gd, pa_nom=pa, gd_nom_max_deg=float(np.max(gd)), gd_nom_mean_deg=float(np.mean(gd)),
                   pa_nom_max=float(np.max(pa)), pa_nom_mean=float(np.mean(pa)))
    return out


def first_order_change(model: IniModel, nominal: IniModel) -> float:
    """Largest relative change of the numeric first-order data (m.state) and TL power."""
    a, b = asdict(model.state(0)), asdict(nominal.state(0))
    worst = 0.0
    for k in a:
        for x, y in zip(np.ravel(a[k]), np.ravel(b[k])):
            worst = max(worst, abs(x - y) / max(abs(y), 1e-12))
    return worst


# ---------------------------------------------------------- pupil measurements
def bundle(model: IniModel, nominal: IniModel, rho: np.ndarray):
    """The on-axis EI's centre-pixel bundle (nominal display point) traced in ``model``:
    VW positions and slopes (R, 2), and the nominal paraxial VW states (R, 4)."""
    subs = sample(nominal, lenslets=[CENTER], depths=[0], fields=np.zeros((1, 2)))
    b = trace(model, subs, rho)
    if not np.all(b.ok):
        raise RuntimeError("rays of the on-axis bundle failed")
    s = np.broadcast_to(subs.display[0, 0], rho.shape)
    c = np.broadcast_to(subs.center[0], rho.shape)
    return b.pos[0, 0], b.slopes()[0, 0], nominal.paraxial_vw(0, s, c, rho)


def pupil_rho(n: int = 15) -> np.ndarray:
    v = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(v, v, indexing="xy")
    return np.concatenate([pupil.MARGINAL, np.stack([X.ravel(), Y.ravel()], axis=1)])


def measure_pupil(geom: Geometry, inj: dict, nominal: IniModel, nominal_bundle=None) -> dict:
    """Pupil SA (waves PV, rho^4 fit at the eyepiece) and pupil tilt (deg) of the
    on-axis centre-pixel bundle, from traced rays vs the zero-injection trace."""
    rho = pupil_rho()
    _, model = build(geom, inj)
    pos, sl, _ = bundle(model, nominal, rho)
    pos0, sl0, par0 = nominal_bundle or bundle(nominal, nominal, rho)
    z = geom.f_ep  # EP -> VW
    h = pos0 - z * sl0  # ray heights on the eyepiece (nominal)
    a = 0.5 * abs(h[0, 0] - h[1, 0])  # paraxial footprint radius there (marginal rays +-x)
    u = (h - h[:4].mean(axis=0)) / a  # normalized pupil coordinate on the eyepiece
    dt = sl - sl0  # slope change = -grad W (the plate is in contact with the eyepiece)
    rho2 = np.sum(u * u, axis=1)
    # W = w1 ux + w2 uy + W020 rho^2 + W040 rho^4; grad_h W = grad_u W / a
    Gx = np.stack([np.ones_like(rho2), np.zeros_like(rho2), 2 * u[:, 0], 4 * rho2 * u[:, 0]], axis=1) / a
    Gy = np.stack([np.zeros_like(rho2), np.ones_like(rho2), 2 * u[:, 1], 4 * rho2 * u[:, 1]], axis=1) / a
    G = np.concatenate([Gx, Gy])
    coef, *_ = np.linalg.lstsq(G, -np.concatenate([dt[:, 0], dt[:, 1]]), rcond=None)
    fit_rms = float(np.sqrt(np.mean((G @ coef + np.concatenate([dt[:, 0], dt[:, 1]])) ** 2)))
    lam = nominal.lam * 1e-6
    shift = np.mean(pos[:4] - pos0[:4], axis=0)  # footprint centroid displacement (mm)
    outward = (pos0[:4] - pos0[:4].mean(axis=0)) / np.linalg.norm(pos0[:4] - pos0[:4].mean(axis=0), axis=1)[:, None]
    return {"w040_waves": float(coef[3] / lam), "w020_waves": float(coef[2] / lam),
            "slope_fit_rms_rad": fit_rms, "footprint_radius_ep_mm": float(a),
            "tilt_deg": float(math.degrees(math.atan(np.hypot(*shift) / z))),
            "footprint_shift_mm": [float(v) for v in shift],
            "marginal_radial_shift_mm": float(np.mean(np.sum((pos[:4] - pos0[:4]) * outward, axis=1)))}


# --------------------------------------------------------------------- solving
def solve_amplitude(measure, target: float, probe: float, tol: float = 1e-7, max_iter: int = 12) -> float:
    """Coefficient x with measure(x) = target (secant from 0, where the measure is 0)."""
    x0, y0 = 0.0, 0.0
    x1 = probe
    y1 = measure(x1)
    for _ in range(max_iter):
        if abs(y1 - target) <= tol * abs(target):
            return x1
        x0, y0, x1 = x1, y1, x1 + (target - y1) * (x1 - x0) / (y1 - y0)
        y1 = measure(x1)
    raise RuntimeError(f"amplitude for target {target} did not converge ({y1})")


DISTORTION_CASES = {
    # kind: (injection key, measure key, sign of the target)
    "barrel": ("radial_A4", "corner_pct", -1.0),
    "pincushion": ("radial_A4", "corner_pct", +1.0),
    "keystone": ("keystone", "keystone_pct", +1.0),
}
PUPIL_CASES = {
    "pupil SA": ("pupil_sa_A4", "w040_waves", -0.01),
    "pupil tilt": ("pupil_tilt", "tilt_deg", 0.01),
}


def distortion_case(geom, kind: str, pct: float, fo=None) -> dict:
    key, mkey, sign = DISTORTION_CASES[kind]
    fo = fo or closed_form(geom)
    coef = solve_amplitude(lambda x: measure_distortion(geom, {key: x}, fo)[mkey], sign * pct,
                           1e-5 if key == "radial_A4" else 1e-3)
    inj = {key: coef}
    return {"kind": kind, "target_pct": pct, "injection": inj, "measured": measure_distortion(geom, inj, fo)}


def pupil_case(geom, kind: str, value: float, nominal: IniModel, nominal_bundle=None) -> dict:
    key, mkey, probe = PUPIL_CASES[kind]
    coef = solve_amplitude(lambda x: measure_pupil(geom, {key: x}, nominal, nominal_bundle)[mkey], value, probe)
    inj = {key: coef}
    return {"kind": kind, "target": value, "injection": inj,
            "measured": measure_pupil(geom, inj, nominal, nominal_bundle)}


# --------------------------------------------------------------------- figures
def plot_grids(cases, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12.5, 8.6))
    for ax in axes.ravel()[len(cases):]:
        ax.set_visible(False)
    for ax, c in zip(axes.ravel(), cases):
        for vv, col, lw in ((c["v_par"], "k", 1.0), (c["v"], "r", 1.0)):
            deg = np.degrees(np.arctan(vv))
            for j in range(N_LENS):
                ax.plot(deg[j, :, 0], deg[j, :, 1], color=col, lw=lw)
            for i in range(M_LENS):
                ax.plot(deg[:, i, 0], deg[:, i, 1], color=col, lw=lw)
            ax.plot(deg[..., 0].ravel(), deg[..., 1].ravel(), ".", color=col, ms=2.5)
        mm = c["measured"]
        label = (f"keystone {abs(mm['keystone_pct']):.2f}%" if c["kind"] == "keystone"
                 else f"{c['kind']} {abs(mm['corner_pct']):.2f}% (at the corner)")
        ax.set_title(f"{label}\nGD max {c['gd_max_deg']:.3f}°, mean {c['gd_mean_deg']:.3f}°", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlim(-23, 23)
        ax.set_ylim(-23, 23)
        ax.set_xlabel("visual angle x (deg)")
        ax.set_ylabel("visual angle y (deg)")
        ax.grid(False)
    fig.suptitle("Global distortion of the 11 x 11 virtual EI centres (CDP 1 D): "
                 "paraxial (black) vs real (red)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def plot_footprints(cases, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 3, figsize=(12, 8.4))
    for ax in axes.ravel()[len(cases):]:
        ax.set_visible(False)
    for ax, c in zip(axes.ravel(), cases):
        env, env_p = c["envelope"], c["envelope_par"]
        ax.fill(env_p[:, 0], env_p[:, 1], fill=False, ec="k", lw=1.2)
        ax.fill(env[:, 0], env[:, 1], fill=False, ec="r", lw=1.2)
        ax.plot(c["marginal_par"][:, 0], c["marginal_par"][:, 1], "ko", ms=4)
        ax.plot(c["marginal"][:, 0], c["marginal"][:, 1], "r^", ms=4)
        mm = c["measured"]
        label = (f"pupil SA {mm['w040_waves']:.3g} λ PV" if c["kind"] == "pupil SA"
                 else f"pupil tilt {mm['tilt_deg']:.3g}°")
        ax.set_title(f"{label}\nPA = {c['pa_nom']:.4f}", fontsize=10)
        ax.set_aspect("equal")
        ax.set_xlim(-0.85, 0.85)
        ax.set_ylim(-0.85, 0.85)
        ax.set_xlabel("x on VW (mm)")
        ax.set_ylabel("y on VW (mm)")
    fig.suptitle("Footprint of the on-axis EI's centre pixel on the viewing window (d_v = 1 mm): "
                 "paraxial (black) vs real (red)", fontsize=11)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------ main
def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items() if k not in ("res",)}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        return float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def run(out: Path, distortion_pcts=(1.0, 2.0, 3.0, 4.0, 5.0), sa_waves=(0.25, 0.5, 1.0),
        tilts_deg=(0.25, 0.5, 1.0), verbose: bool = True) -> dict:
    t0 = time.perf_counter()
    say = print if verbose else (lambda *a, **k: None)
    geom = solve_geometry()
    fo = closed_form(geom)
    d0, m0 = build(geom)
    st = m0.state(0)
    say(f"geometry: f_ep = {geom.f_ep:.6f} mm, l = {geom.l:.6f} mm, g = {geom.g:.6f} mm, "
        f"TL {st.tunable_power_diopters:.6f} D (closed form {geom.tl_diopters:.6f} D)")
    say(f"first order: EI-centre step {st.delta_theta_eic_deg[0]:.4f}°, outer centres at "
        f"±{math.degrees(math.atan(5 * math.tan(math.radians(st.delta_theta_eic_deg[0])))):.4f}°, "
        f"d_v = {st.d_v[0]:.6f} mm, closed-form d_v = {fo.d_v:.6f} mm, z_CDP = {fo.z_cdp:.3f} mm")
    lens = all_lenslets()

    # Zero injection and the independent cross-check of lfsim's chief rays.
    zero = lfsim_metrics(m0, lens, m0)
    v0, vp0 = chief_rays(d0, geom, fo)
    ch = zero["res"]["sets"].slices["chief"].start
    r_lf = -zero["res"]["r"][:, 0, ch].reshape(N_LENS, M_LENS, 2)
    rp_lf = -zero["res"]["r_par"][:, 0, ch].reshape(N_LENS, M_LENS, 2)
    cross = {"paraxial_max_abs_diff": float(np.max(np.abs(rp_lf - vp0))),
             "real_max_abs_diff": float(np.max(np.abs(r_lf - v0))),
             "tl_diopters_model_minus_closed_form": st.tunable_power_diopters - geom.tl_diopters}
    say(f"zero injection: GD max {zero['gd_max_deg']:.3g}°, PA max {zero['pa_max']:.3g}; "
        f"lfsim vs independent chief rays: paraxial {cross['paraxial_max_abs_diff']:.2g}, "
        f"real {cross['real_max_abs_diff']:.2g} (tangent)")

    # Distortion sweeps.
    dist = []
    for kind in DISTORTION_CASES:
        for pct in distortion_pcts:
            c = distortion_case(geom, kind, pct, fo)
            d, m = build(geom, c["injection"])
            met = lfsim_metrics(m, lens, m0)
            v, vp = chief_rays(d, geom, fo)
            r_lf = -met["res"]["r"][:, 0, ch].reshape(N_LENS, M_LENS, 2)
            c.update(gd_max_deg=met["gd_max_deg"], gd_mean_deg=met["gd_mean_deg"],
                     pa_max=met["pa_max"], pa_mean=met["pa_mean"],
                     gd_ref_diff_deg=float(np.max(np.abs(met["gd"] - met["gd_nom"]))),
                     lfsim_vs_independent_real=float(np.max(np.abs(r_lf - v))),
                     first_order_change=first_order_change(m, m0),
                     gd_grid_deg=met["gd"].reshape(N_LENS, M_LENS), v=v, v_par=vp)
            dist.append(c)
            mm = c["measured"]
            say(f"{kind:10s} {pct:4.1f}%: corner {mm['corner_pct']:+.4f}%, edge {mm['edge_pct']:+.4f}%, "
                f"keystone {mm['keystone_pct']:+.4f}% | GD max {c['gd_max_deg']:.4f}°, mean "
                f"{c['gd_mean_deg']:.4f}° | PA max {c['pa_max']:.2g} | first-order change "
                f"{c['first_order_change']:.1e}")

    # Pupil aberration sweeps: the on-axis EI's centre pixel (Fig. 5).
    rho = pupil_rho()
    nb = bundle(m0, m0, rho)
    per = pupil.perimeter(24)
    sub0 = sample(m0, lenslets=[CENTER], depths=[0], fields=np.zeros((1, 2)))
    env_par = m0.paraxial_vw(0, np.broadcast_to(sub0.display[0, 0], per.shape),
                             np.broadcast_to(sub0.center[0], per.shape), per)[:, :2]
    marg_par = m0.paraxial_vw(0, np.broadcast_to(sub0.display[0, 0], (4, 2)),
                              np.broadcast_to(sub0.center[0], (4, 2)), pupil.MARGINAL)[:, :2]
    pup = []
    for kind, values in (("pupil SA", sa_waves), ("pupil tilt", tilts_deg)):
        for val in values:
            c = pupil_case(geom, kind, val, m0, nb)
            _, m = build(geom, c["injection"])
            own = lfsim_metrics(m, [CENTER])  # lfsim's evaluate with its own reference
            nom = lfsim_metrics(m, [CENTER], m0)  # the nominal (paper's) reference
            env = trace(m, sub0, per).pos[0, 0]
            marg = trace(m, sub0, pupil.MARGINAL).pos[0, 0]
            c.update(pa_nom=nom["pa_nom_max"], pa_lfsim=own["pa_max"], gd_nom_deg=nom["gd_nom_max_deg"],
                     gd_lfsim_deg=own["gd_max_deg"], first_order_change=first_order_change(m, m0),
                     envelope=env, envelope_par=env_par, marginal=marg, marginal_par=marg_par)
            if kind == "pupil tilt":  # the tilt acts on every EI: the whole 11 x 11 grid
                allm = lfsim_metrics(m, lens, m0)
                c.update(all_pa_nom_max=allm["pa_nom_max"], all_pa_nom_mean=allm["pa_nom_mean"],
                         all_gd_nom_max_deg=allm["gd_nom_max_deg"], all_pa_lfsim_max=allm["pa_max"])
            pup.append(c)
            mm = c["measured"]
            say(f"{kind:10s} {val:5.2f}: W040 {mm['w040_waves']:.4f} waves, W020 {mm['w020_waves']:+.2e}, "
                f"tilt {mm['tilt_deg']:.4f}° | PA (nominal ref) {c['pa_nom']:.4f}, PA (lfsim evaluate) "
                f"{c['pa_lfsim']:.2e} | GD {c['gd_nom_deg']:.2e}° | first-order change {c['first_order_change']:.1e}")

    table = table_rows(dist, pup)
    say("")
    say(format_table(table))
    doc = {
        "description": __doc__.split("\n\n")[0],
        "geometry": asdict(geom) | {"tl_diopters_closed_form": geom.tl_diopters, "n_plate": N_PLATE,
                                    "pair_gap_mm": PAIR_GAP, "norm_radius_mm": NORM_R},
        "first_order": st.as_dict(),
        "zero_injection": {k: zero[k] for k in ("gd_max_deg", "gd_mean_deg", "pa_max", "pa_mean")},
        "crosscheck_independent": cross,
        "paper": PAPER,
        "table": table,
        "distortion": [{k: v for k, v in c.items() if k not in ("v", "v_par")} for c in dist],
        "pupil": [{k: v for k, v in c.items() if k not in ("envelope", "envelope_par", "marginal", "marginal_par")}
                  for c in pup],
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    out = Path(out)
    write_json(out / "synthetic_aberrations.json", _jsonable(doc))
    wanted = [("barrel", 1.0), ("barrel", 5.0), ("pincushion", 1.0), ("pincushion", 5.0),
              ("keystone", 2.0), ("keystone", 5.0)]
    grid_cases = [c for k, p in wanted for c in dist if c["kind"] == k and c["target_pct"] == p]
    grid_cases += [c for c in dist if all(c is not x for x in grid_cases)][:max(0, 6 - len(grid_cases))]
    plot_grids(grid_cases, out / "synthetic_distortion_gd.png")
    plot_footprints(pup[:6], out / "synthetic_pupil_pa.png")
    say(f"wrote {out / 'synthetic_aberrations.json'}, {out / 'synthetic_distortion_gd.png'}, "
        f"{out / 'synthetic_pupil_pa.png'} ({doc['wall_s']} s)")
    return doc


def table_rows(dist, pup) -> list[dict]:
    paper_gd = {("barrel", 1.0): 0.36, ("barrel", 5.0): 1.78}
    paper_pa = {("pupil SA", 0.25): 0.059, ("pupil SA", 1.0): 0.23}
    rows = []
    for c in dist:
        mm = c["measured"]
        rows.append({"case": f"{c['kind']} {c['target_pct']:g}%",
                     "measured": (f"corner {mm['corner_pct']:+.3f}%, edge {mm['edge_pct']:+.3f}%"
                                  if c["kind"] != "keystone" else
                                  f"keystone {mm['keystone_pct']:+.3f}%, corner {mm['corner_pct']:+.3f}%"),
                     "gd_max_deg": c["gd_max_deg"], "gd_mean_deg": c["gd_mean_deg"], "pa": c["pa_max"],
                     "paper": paper_gd.get((c["kind"], c["target_pct"]))})
    for c in pup:
        mm = c["measured"]
        rows.append({"case": f"{c['kind']} {c['target']:g}" + (" waves PV" if c["kind"] == "pupil SA" else " deg"),
                     "measured": (f"W040 {mm['w040_waves']:.4f} waves (W020 {mm['w020_waves']:+.4f})"
                                  if c["kind"] == "pupil SA" else
                                  f"tilt {mm['tilt_deg']:.4f} deg, shift {np.hypot(*mm['footprint_shift_mm']):.4f} mm"),
                     "gd_max_deg": c["gd_nom_deg"], "gd_mean_deg": None, "pa": c["pa_nom"],
                     "pa_lfsim_own_reference": c["pa_lfsim"],
                     "paper": paper_pa.get((c["kind"], c["target"]))})
    return rows


def format_table(rows) -> str:
    head = f"{'case':24s} {'measured injection':42s} {'GD max °':>9s} {'GD mean °':>9s} {'PA':>8s} {'paper':>7s}"
    lines = [head, "-" * len(head)]
    for r in rows:
        f = lambda v, fmt: "" if v is None else format(v, fmt)  # noqa: E731
        lines.append(f"{r['case']:24s} {r['measured']:42s} {f(r['gd_max_deg'], '9.4f'):>9s} "
                     f"{f(r['gd_mean_deg'], '9.4f'):>9s} {f(r['pa'], '8.4f'):>8s} {f(r['paper'], '7.3g'):>7s}")
    return "\n".join(lines)


def main(argv=None):
    ap = OneLineParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img"), help="folder for the JSON and the figures")
    args = ap.parse_args(argv)
    run(Path(args.out))


if __name__ == "__main__":
    main()
