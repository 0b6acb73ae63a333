"""How flat can four singlets make the relay's field, at a design's first order? A paraxial search.

The wearable design's relay (four spherical singlets and a tunable lens between
the lenslet array's aperture plane ``AA`` and the prism) curves its field, and
the prism has to live with that. This script asks how flat the relay's field
can be made while the relay keeps **exactly the same first order**, so that the
InI first-order model (CDP at each state, EI pitch, angular pixel, FOV) is
unchanged:

* the y–ν matrix ``M`` from the plane of ``AA`` to a reference plane behind
  the relay equals the design's at the 1 D state, and its derivative in the
  tunable lens's power has the same direction, ``dM/dφ = dM₀/dφ · (1/k)``; the
  tunable lens's powers then map one to one (``φ − φ₁ = k·(φ₀ − φ₀₁)``) and
  must stay inside its range at every CDP state;
* everything behind the relay (the prism, the viewing window) moves along the
  axis with the relay's end, so the track changes by the relay's change of
  length.

The objective is the relay's third-order field curvature, sagittal and
tangential: ``(S_III + S_IV)² + (3·S_III + S_IV)²`` relative to the design's
own Petzval term ``S_IV²`` (Seidel sums of :func:`seidel`), with spherical
aberration and coma held small (``|S_I|, |S_II| ≤ 1e-3`` mm). The Petzval sum
alone is the wrong target: minimized on its own it reaches 0 in the package
with lenses whose astigmatism is tens of times the design's.

Each singlet has two curvatures, a centre thickness and a glass from
``--glasses``; the six air gaps are free. The rules (:class:`Rules`, mm) are
the package's:

* every face's paraxial footprint of the design's own ray bundle (the real rays
  of ``lfsim.ini.package.ray_set`` at ``AA``: corner, edge and centre lenslets,
  EI corners, edges and centres, chief and marginal rays, every CDP state)
  within ``--clear-diameter``/2, and the tunable lens's within the design's own
  (paraxial) footprint there, which fits its 10 mm aperture;
* surface slope ``|c|·h ≤ 0.7`` at the lens's semi-diameter ``h`` (the
  footprint plus 0.3 mm, at most half the clear diameter: the semi-diameter a
  written design gets, so its edge thickness is the one checked here);
* glass and air at least 1 mm at the centre and the edge; 16 mm from the last
  face to the reference plane (room for the prism's entrance);
* the relay's length ≤ the design's + (track limit − the design's track);
* axial and lateral colour (first-order chromatic sums ``C_I``, ``C_II``,
  F − C, for the same rays) no larger than the design's own relay's times
  ``--colour-max`` (default 1). ``lfsim optimize``'s InI merit is
  monochromatic unless its ``colour`` weight is set, so colour that the relay
  adds is colour the optimized design keeps: four singlets in a dense flint-like lanthanum glass flatten the
  field best but, without this rule, fringe the retinal image.

For each assignment of glasses and each track limit (tightest first), SLSQP
starts from the best relay of the next tighter limit, the design's relay in
these glasses (each lens's matrix kept) and random perturbations of it, and
keeps the least field curvature. It is paraxial: it says what the first order
and the parts allow, not what the optimizer will make of it. ``--write``
writes the best relay of each limit as a design file beside the JSON (the
original with the relay swapped and the prism moved), ready for ``lfsim
optimize``. Run::

    python examples/relay_petzval.py --out DIR [--track-limits 150,175,200,250]

It prints one line per limit and glass assignment and writes
``relay_petzval.json`` and ``relay_petzval.png``.
"""

from __future__ import annotations

import copy
import itertools
import json
import math
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tomli_w
from relay_variants import LENSES, _curvature, _shift_after_relay, off_axis  # examples/, beside this script
from scipy.optimize import minimize

from lfsim.cli import OneLineParser
from lfsim.optics.materials import lookup

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_GLASSES = ("N-LAK22", "N-BK7", "N-SF11", "N-LASF31A")


# ----------------------------------------------------------------- the design's relay

@dataclass
class Relay:
    """A four-singlet relay around a thin tunable lens: ``gaps`` (6,) AA → L1, L1 → L2,
    L2 → TL, TL → L3, L3 → L4, L4 → reference plane; ``c1``, ``c2``, ``t``, ``n`` (4,); ``dn``
    (4,) each glass's principal dispersion n_F − n_C (0: no colour)."""

    gaps: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    t: np.ndarray
    n: np.ndarray
    dn: np.ndarray | None = None

    def __post_init__(self):
        if self.dn is None:
            self.dn = np.zeros(4)

    @property
    def length(self) -> float:
        return float(np.sum(self.gaps) + np.sum(self.t))

    def petzval(self) -> float:
        return float(np.sum((self.n - 1.0) * (self.c1 - self.c2) / self.n))

    def pack(self) -> np.ndarray:
        return np.concatenate([self.gaps, self.c1, self.c2, self.t])

    @classmethod
    def unpack(cls, v, n, dn=None) -> Relay:
        v = np.asarray(v, dtype=np.float64)
        return cls(v[:6].copy(), v[6:10].copy(), v[10:14].copy(), v[14:18].copy(), np.asarray(n, dtype=np.float64),
                   None if dn is None else np.asarray(dn, dtype=np.float64))


def dispersion(glass: str) -> float:
    """A glass's principal dispersion n_F − n_C (486.13 and 656.27 nm)."""
    m = lookup(glass)
    return float(m.index(486.1327) - m.index(656.2725))


def read_relay(raw: dict, lam: float, powers=None):
    """(Relay, the tunable lens's power at each CDP state in mm⁻¹) of a design; ``powers``
    (diopters) where the design lists none (they are then solved: ``lfsim ini`` gives them)."""
    S = raw["surfaces"]
    names = [s.get("name") for s in S]
    ia, it = names.index("AA"), names.index(raw["ini"]["tunable"]["surface"])
    idx = [names.index(x) for x in LENSES]
    if not (ia < idx[0] < idx[1] < it < idx[2] < idx[3]):
        raise ValueError("expected AA, two singlets, the tunable lens, two singlets in that order")
    for i in idx:
        off_axis(S[i], S[i + 1])
    c1 = np.array([_curvature(S[i]) for i in idx])
    c2 = np.array([_curvature(S[i + 1]) for i in idx])
    t = np.array([float(S[i]["thickness"]) for i in idx])
    n = np.array([float(lookup(S[i]["material"]).index(lam)) for i in idx])
    dn = np.array([dispersion(S[i]["material"]) for i in idx])
    th = lambda i: float(S[i]["thickness"])  # noqa: E731
    gaps = np.array([th(ia), th(idx[0] + 1), th(idx[1] + 1), th(it), th(idx[2] + 1), th(idx[3] + 1)])
    inside = set(range(ia + 1, idx[3] + 2)) - {it, *idx, *(j + 1 for j in idx)}
    if inside:
        raise ValueError(f"surface {names[min(inside)]!r} inside the relay: only four singlets and the tunable lens")
    phis = np.asarray(raw["ini"]["tunable"].get("power_diopters", powers), dtype=np.float64) * 1e-3
    return Relay(gaps, c1, c2, t, n, dn), phis


def _T(d):
    return np.array([[1.0, d], [0.0, 1.0]])


def _L(phi):
    return np.array([[1.0, 0.0], [-phi, 1.0]])


def _steps(r: Relay, phi: float):
    """The relay as (kind, matrix) steps from the AA plane: ``"face"`` steps are refractions
    (their heights are the footprints), ``"tunable"`` the thin tunable lens."""
    out = []

    def lens(j):
        out.append(("face", _L((r.n[j] - 1.0) * r.c1[j])))
        out.append(("gap", _T(r.t[j] / r.n[j])))
        out.append(("face", _L((1.0 - r.n[j]) * r.c2[j])))

    out.append(("gap", _T(r.gaps[0])))
    lens(0)
    out.append(("gap", _T(r.gaps[1])))
    lens(1)
    out.append(("gap", _T(r.gaps[2])))
    out.append(("tunable", _L(phi)))
    out.append(("gap", _T(r.gaps[3])))
    lens(2)
    out.append(("gap", _T(r.gaps[4])))
    lens(3)
    out.append(("gap", _T(r.gaps[5])))
    return out


def matrices(r: Relay, phi: float):
    """``(faces, M_a, M_b)``: the matrices AA → each of the 8 faces, and the split
    ``M = M_b · L(φ) · M_a`` about the tunable lens (``M_a``: AA → the tunable lens)."""
    M, faces, Ma, Mb = np.eye(2), [], None, None
    for kind, A in _steps(r, phi):
        if kind == "face":
            faces.append(M)
        elif kind == "tunable":
            Ma, Mb = M, np.eye(2)
        M = A @ M
        if Mb is not None and kind != "tunable":
            Mb = A @ Mb
    return faces, Ma, Mb


def seidel(r: Relay, phi: float, marginal, chief) -> np.ndarray:
    """Third-order Seidel sums (S_I spherical, S_II coma, S_III astigmatism, S_IV Petzval) and the
    first-order chromatic sums (C_I axial, C_II lateral colour, F − C) of the singlets' eight faces
    for a ``marginal`` and a ``chief`` ray (y, dy/dz) given at the AA plane, through the tunable
    lens of power ``phi`` (ideal: it adds none). W. T. Welford, *Aberrations of Optical Systems*
    (1986), ch. 8 and 9: ``S_I = −ΣA²yΔ(u/n)``, ``S_II = −ΣAĀyΔ(u/n)``, ``S_III = −ΣĀ²yΔ(u/n)``,
    ``S_IV = −ΣH²cΔ(1/n)``, ``C_I = ΣAyΔ(δn/n)``, ``C_II = ΣĀyΔ(δn/n)`` with ``A = n(u + yc)``,
    the Lagrange invariant ``H = n(uȳ − ūy)`` and ``δn = n_F − n_C`` (``r.dn``)."""
    (y, u), (yb, ub) = marginal, chief
    H = u * yb - ub * y
    n, dn = 1.0, 0.0
    S = np.zeros(6)

    def face(c, n2, dn2):
        nonlocal y, u, yb, ub, n, dn
        A, Ab = n * (u + y * c), n * (ub + yb * c)
        u2, ub2 = (A / n2) - y * c, (Ab / n2) - yb * c
        d = u2 / n2 - u / n
        dc = dn2 / n2 - dn / n
        S[:] += [-A * A * y * d, -A * Ab * y * d, -Ab * Ab * y * d, -H * H * c * (1.0 / n2 - 1.0 / n),
                 A * y * dc, Ab * y * dc]
        u, ub, n, dn = u2, ub2, n2, dn2

    def move(t):
        nonlocal y, yb
        y, yb = y + t * u, yb + t * ub

    def lens(j):
        face(r.c1[j], r.n[j], r.dn[j])
        move(r.t[j])
        face(r.c2[j], 1.0, 0.0)

    def tunable():
        nonlocal u, ub
        u, ub = u - y * phi, ub - yb * phi

    for step in (lambda: move(r.gaps[0]), lambda: lens(0), lambda: move(r.gaps[1]), lambda: lens(1),
                 lambda: move(r.gaps[2]), tunable, lambda: move(r.gaps[3]), lambda: lens(2),
                 lambda: move(r.gaps[4]), lambda: lens(3)):
        step()
    return S


def sag(c, h):
    return c * h * h / (1.0 + np.sqrt(np.maximum(1.0 - (c * h) ** 2, 1e-12)))


# ----------------------------------------------------------------- the ray bundle

def bundle(design_path: Path, first_face: str = LENSES[0]):
    """The design's ray bundle at the AA plane, from the rays' hits on AA and on the first relay
    face (``first_face``): ``(rays, marginal)``. ``rays`` (N, 5): the real rays (x, y, dx/dz, dy/dz, CDP state) of
    the package figures (:func:`lfsim.ini.package.ray_set`); ``marginal`` (K, 2): per CDP state,
    the central lenslet's centre-field +x marginal ray relative to its chief ray (y, dy/dz)."""
    from lfsim.design.design import load
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import FIELDS, PUPIL, ray_set
    from lfsim.ini.subsystems import trace_rays_jacobian

    model = IniModel(load(design_path))
    names = [s.name for s in model.system.surfaces]
    ia, i1 = names.index("AA"), names.index(first_face)
    s, m, n, rho, k, lens = ray_set(model)
    J = trace_rays_jacobian(model, s, m, n, rho, k, [], record=[ia, i1], derivatives=False)
    frames = model.tracer.frames_numpy(model.tracer.params(values=model.values0))
    p0 = J.surf[:, 0, :] + model.lenslet_center(m, n)
    p1 = J.surf[:, 1, :]
    raw = tomllib.loads(Path(design_path).read_text())
    c = _curvature(next(x for x in raw["surfaces"] if x.get("name") == first_face))
    dz = frames[i1][1][2] + sag(c, np.hypot(p1[:, 0], p1[:, 1])) - frames[ia][1][2]
    rays = np.column_stack([p0, (p1 - p0) / dz[:, None], k])
    K, L, F, R = len(model.depths), len(lens), len(FIELDS), len(PUPIL)
    j = int(np.nonzero((lens[:, 0] == model.arr.m // 2) & (lens[:, 1] == model.arr.n // 2))[0][0])
    marginal = []
    for kk in range(K):
        base = ((kk * L + j) * F + 0) * R
        chief, edge = rays[base], rays[base + 1]  # PUPIL[0] the chief ray, PUPIL[1] the +x marginal ray
        if J.status[base] != 0 or J.status[base + 1] != 0:
            raise ValueError("the central lenslet's centre-field rays fail")
        marginal.append((edge[0] - chief[0], edge[2] - chief[2]))
    return rays[J.status == 0], np.array(marginal)


def footprints(r: Relay, phis, rays: np.ndarray):
    """Paraxial footprint radii of ``rays`` (N, 5) on the 8 faces and on the tunable lens, each
    ray through the tunable power of its own CDP state (``phis``, mm⁻¹)."""
    face = np.zeros(8)
    tun = 0.0
    for k, phi in enumerate(phis):
        sel = rays[:, 4] == k
        if not sel.any():
            continue
        x = rays[sel]
        faces, Ma, _ = matrices(r, phi)
        for j, M in enumerate(faces):
            face[j] = max(face[j], np.max(np.hypot(M[0, 0] * x[:, 0] + M[0, 1] * x[:, 2],
                                                   M[0, 0] * x[:, 1] + M[0, 1] * x[:, 3])))
        tun = max(tun, np.max(np.hypot(Ma[0, 0] * x[:, 0] + Ma[0, 1] * x[:, 2],
                                       Ma[0, 0] * x[:, 1] + Ma[0, 1] * x[:, 3])))
    return face, tun


# ----------------------------------------------------------------- the search

@dataclass
class Rules:
    """The package's rules for the relay (mm)."""

    clear_diameter: float = 23.2
    max_slope: float = 0.7
    margin: float = 0.3
    min_glass: float = 1.0
    min_air: float = 1.0
    min_back: float = 16.0
    max_length: float = math.inf
    tunable_range: tuple = (8.3e-3, 20.0e-3)
    #: largest |S_I| and |S_II| (mm, for the Seidel rays of :class:`Search`): 1e-3 is about 0.2 λ
    #: of W040 = S_I/8; the design's own relay has 6e-5 and 4e-5
    spherical_max: float = 1e-3
    coma_max: float = 1e-3
    #: largest |C_I| and |C_II| (axial and lateral colour, F − C) as a multiple of the design's own
    #: relay's: a relay may not add colour that the monochromatic merit of ``lfsim optimize``
    #: would not see (inf: no limit)
    colour_max: float = 1.0


class Search:
    """Least Petzval sum of the relay at ``ref``'s first order, under ``rules``, for given glasses."""

    def __init__(self, ref: Relay, phis, rays: np.ndarray, marginal, rules: Rules, k1: int = 1):
        self.ref, self.phis, self.rays, self.rules = ref, np.asarray(phis, dtype=np.float64), rays, rules
        self.k1 = k1
        _, Ma, Mb = matrices(ref, self.phis[k1])
        self.M0 = Mb @ _L(self.phis[k1]) @ Ma
        self.a0, self.b0 = Ma[0, :].copy(), Mb[:, 1].copy()
        self.tun0 = footprints(ref, self.phis, rays)[1]
        # Seidel rays at the 1 D state: the axial beamlet's marginal ray, and the chief ray of the
        # corner lenslet's EI centre through the tunable lens's centre (the same ray for every
        # candidate: M_a's first row keeps its direction).
        h = float(np.max(np.hypot(rays[:, 0], rays[:, 1])))
        self.marginal, self.chief = tuple(marginal[k1]), (h, -Ma[0, 0] * h / Ma[0, 1])
        self.seidel0 = seidel(ref, self.phis[k1], self.marginal, self.chief)

    # x = (gaps 6, c1 4, c2 4, t 4, phi1); n, dn (4,): the glasses' indices and dispersions
    def _relay(self, x, n, dn=None):
        return Relay.unpack(x[:18], n, dn)

    def state_powers(self, x, n):
        """(tunable powers per CDP state, k) at ``x``."""
        r = self._relay(x, n)
        _, Ma, Mb = matrices(r, x[18])
        alpha = Ma[0, :] @ self.a0 / (self.a0 @ self.a0)
        beta = Mb[:, 1] @ self.b0 / (self.b0 @ self.b0)
        k = 1.0 / (alpha * beta)
        return x[18] + k * (self.phis - self.phis[self.k1]), k

    def equalities(self, x, n):
        r = self._relay(x, n)
        _, Ma, Mb = matrices(r, x[18])
        M = Mb @ _L(x[18]) @ Ma
        a, b = Ma[0, :], Mb[:, 1]
        return np.array([M[0, 0] - self.M0[0, 0], (M[0, 1] - self.M0[0, 1]) / 10.0,
                         (M[1, 0] - self.M0[1, 0]) * 10.0,
                         (a[0] * self.a0[1] - a[1] * self.a0[0]) / (np.linalg.norm(self.a0) ** 2),
                         (b[0] * self.b0[1] - b[1] * self.b0[0]) / (np.linalg.norm(self.b0) ** 2)])

    def semi_diameters(self, x, n):
        r = self._relay(x, n)
        phis, _ = self.state_powers(x, n)
        face, tun = footprints(r, phis, self.rays)
        return face, tun

    def lens_semi_diameters(self, face):
        """Each lens's semi-diameter: its larger face footprint plus ``margin``, at most half the
        clear diameter; the rules hold at it and :func:`write_variant` writes it."""
        R = self.rules
        return np.minimum(R.clear_diameter / 2.0, np.maximum(face[0::2], face[1::2]) + R.margin)

    def inequalities(self, x, n, dn):
        """Every rule as ``g ≥ 0``."""
        R, r = self.rules, self._relay(x, n, dn)
        face, tun = self.semi_diameters(x, n)
        phis, _ = self.state_powers(x, n)
        a = self.lens_semi_diameters(face)
        g = [R.clear_diameter / 2.0 - face, np.array([self.tun0 - tun])]
        g.append(R.max_slope ** 2 - (r.c1 * a) ** 2)
        g.append(R.max_slope ** 2 - (r.c2 * a) ** 2)
        g.append(r.t - R.min_glass)
        g.append(r.t - sag(r.c1, a) + sag(r.c2, a) - R.min_glass)
        g.append(np.array([r.gaps[0] + min(0.0, sag(r.c1[0], a[0])) - R.min_air]))
        for j, gi in ((0, 1), (2, 4)):  # air between the two lenses of each group, centre and rim
            h = min(a[j], a[j + 1])
            g.append(np.array([r.gaps[gi] - R.min_air, r.gaps[gi] - sag(r.c2[j], h) + sag(r.c1[j + 1], h) - R.min_air]))
        g.append(np.array([r.gaps[2] - max(0.0, sag(r.c2[1], a[1])) - R.min_air,
                           r.gaps[3] + min(0.0, sag(r.c1[2], a[2])) - R.min_air]))
        g.append(np.array([r.gaps[5] - R.min_back]))
        if math.isfinite(R.max_length):
            g.append(np.array([R.max_length - r.length]))
        g.append(np.concatenate([(phis - R.tunable_range[0]) * 1e3, (R.tunable_range[1] - phis) * 1e3]))
        S = seidel(r, x[18], self.marginal, self.chief)
        g.append(np.array([R.spherical_max ** 2 - S[0] ** 2, R.coma_max ** 2 - S[1] ** 2]) / R.coma_max ** 2)
        if math.isfinite(R.colour_max):
            c0 = np.abs(self.seidel0[4:6])
            g.append(1.0 - (S[4:6] / (R.colour_max * c0)) ** 2)
        return np.concatenate(g)

    def field_curvature(self, x, n) -> float:
        """The objective: sagittal and tangential field curvature, ``(S_III + S_IV)² + (3·S_III +
        S_IV)²``, relative to the design's own Petzval term S_IV."""
        S3, S4 = seidel(self._relay(x, n), x[18], self.marginal, self.chief)[2:4]
        return float(((S3 + S4) ** 2 + (3.0 * S3 + S4) ** 2) / self.seidel0[3] ** 2)

    def start(self, n_new, rng=None, spread=0.0):
        """The reference relay in the glasses ``n_new``, each lens's matrix kept (curvatures ×
        (n − 1)/(n′ − 1), thickness × n′/n), optionally perturbed."""
        r = self.ref
        f = (r.n - 1.0) / (n_new - 1.0)
        x = np.concatenate([r.gaps, r.c1 * f, r.c2 * f, r.t * n_new / r.n, [self.phis[self.k1]]])
        if rng is not None and spread > 0:
            x[6:14] += rng.normal(0.0, spread * 0.03, 8)
            x[:6] *= np.exp(rng.normal(0.0, spread * 0.2, 6))
        return x

    def solve(self, n_new, dn_new, x0, maxiter=300):
        n_new, dn_new = np.asarray(n_new, dtype=np.float64), np.asarray(dn_new, dtype=np.float64)
        bounds = [(0.5, 120.0)] * 6 + [(-0.2, 0.2)] * 8 + [(1.0, 20.0)] * 4 + [self.rules.tunable_range]
        res = minimize(lambda x: self.field_curvature(x, n_new), x0, method="SLSQP", bounds=bounds,
                       constraints=[{"type": "eq", "fun": lambda x: self.equalities(x, n_new)},
                                    {"type": "ineq", "fun": lambda x: self.inequalities(x, n_new, dn_new)}],
                       options={"maxiter": maxiter, "ftol": 1e-12})
        x = res.x
        feasible = (np.max(np.abs(self.equalities(x, n_new))) < 1e-7
                    and np.min(self.inequalities(x, n_new, dn_new)) > -1e-6)
        return x, self.field_curvature(x, n_new), feasible


# ----------------------------------------------------------------- a design with the found relay

def write_variant(raw: dict, r: Relay, glasses, phis, ref_length: float,
                  semi: np.ndarray | None = None) -> dict:
    """``raw`` with its relay replaced by ``r`` (glasses by name), the tunable lens's powers
    ``phis`` (mm⁻¹, per CDP state), everything behind the relay moved along the axis by the
    change of length, and the optimizer's bounds on relay variables widened to hold the new values."""
    out = copy.deepcopy(raw)
    S = out["surfaces"]
    names = [s.get("name") for s in S]
    tl = out["ini"]["tunable"]["surface"]
    ia, it = names.index("AA"), names.index(tl)
    idx = [names.index(x) for x in LENSES]
    k1 = int(np.argmin(np.abs(np.asarray(out["ini"]["cdp_diopters"], dtype=float) - 1.0)))
    for j, i in enumerate(idx):
        a, b = S[i], S[i + 1]
        for s_ in (a, b):
            s_.pop("radius", None)
        a["curvature"], b["curvature"] = float(r.c1[j]), float(r.c2[j])
        a["thickness"], a["material"] = float(r.t[j]), glasses[j]
        if semi is not None:
            a["semi_diameter"] = b["semi_diameter"] = float(semi[j])
        a["comment"] = f"relay lens {j + 1}, {glasses[j]} (relay of least field curvature, examples/relay_petzval.py)"
    for i, g in zip((ia, idx[0] + 1, idx[1] + 1, it, idx[2] + 1, idx[3] + 1), r.gaps):
        S[i]["thickness"] = float(g)
    S[it]["focal_length"] = float(1.0 / phis[k1])
    if "power_diopters" in out["ini"]["tunable"]:  # else solved again, to the same powers
        out["ini"]["tunable"]["power_diopters"] = [float(p * 1e3) for p in phis]
    _shift_after_relay(out, r.length - ref_length)
    value = {f"{s_['name']}.curvature": s_.get("curvature") for s_ in S if "name" in s_}
    value |= {f"{s_['name']}.thickness": s_.get("thickness") for s_ in S if "name" in s_}
    value["tunable"] = float(phis[k1] * 1e3)
    for v in out.get("optimize", {}).get("variables", []):
        if isinstance(v, dict) and value.get(v.get("name")) is not None:
            x = float(value[v["name"]])
            if "min" in v and x < v["min"]:
                v["min"] = x - 0.25 * abs(x)
            if "max" in v and x > v["max"]:
                v["max"] = x + 0.25 * abs(x)
    out["name"] = f"{raw.get('name', 'design')} (relay of least field curvature: {', '.join(glasses)})"
    return out


# ----------------------------------------------------------------- command line

def search(S: Search, glasses, lam: float, starts: int, seed: int, warm=()):
    """The least field curvature over SLSQP runs from ``warm`` (e.g. the best relay under a
    tighter limit, feasible under this one) and ``starts`` more (the reference relay in these
    glasses, then random perturbations of it): ``(x, objective, feasible runs, origin)`` or
    None. ``origin`` says which start the best run came from ("warm", "reference",
    "random N"), and "reference, unmoved" when SLSQP left the reference relay where it was:
    then no start found a flatter relay than the design's own, re-glassed."""
    n = np.array([float(lookup(g).index(lam)) for g in glasses])
    dn = np.array([dispersion(g) for g in glasses])
    rng = np.random.default_rng(seed)
    best, feasible = None, 0
    x0s = [np.asarray(w, dtype=np.float64) for w in warm]
    x0s += [S.start(n, rng, spread=1.0 if s else 0.0) for s in range(starts)]
    for i, x0 in enumerate(x0s):
        x, P, ok = S.solve(n, dn, x0)
        feasible += ok
        if ok and (best is None or abs(P) < abs(best[1])):
            best = (x, P, i)
    if best is None:
        return None
    x, P, i = best
    k = i - len(warm)
    origin = "warm" if k < 0 else "reference" if k == 0 else f"random {k}"
    if k == 0 and np.allclose(x, x0s[i], rtol=1e-9, atol=1e-12):
        origin = "reference, unmoved"
    return x, P, feasible, origin


def parse_glasses(ap, text: str) -> tuple:
    """Four catalog glasses from a ``--glasses`` value, or the parser's one-line error."""
    a = tuple(g.strip() for g in text.split(","))
    if len(a) != 4:
        ap.error(f"--glasses {text!r}: four glasses, one per singlet")
    for g in a:
        try:
            lookup(g)
        except ValueError as e:
            ap.error(f"--glasses {text!r}: {e}")
    return a


def main(argv=None) -> int:
    ap = OneLineParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_wearable.toml"),
                    help="an InI design with AA, two coaxial singlets, the tunable lens, two coaxial singlets "
                         "(default: %(default)s)")
    ap.add_argument("--out", required=True, help="folder for relay_petzval.json / .png and the written designs")
    ap.add_argument("--track-limits", default="150,175,200",
                    help="track limits (mm), comma separated; 'none' for no limit (default: %(default)s)")
    ap.add_argument("--glasses", action="append",
                    help="four glasses, comma separated, one assignment per flag (default: all N-LAK22, and "
                         "all N-LASF31A)")
    ap.add_argument("--clear-diameter", type=float, default=23.2,
                    help="largest clear diameter of a lens, mm (default: %(default)s, on 25.4 mm parts)")
    ap.add_argument("--starts", type=int, default=10,
                    help="SLSQP runs per limit and glasses besides the warm start (default: %(default)s)")
    ap.add_argument("--colour-max", type=float, default=1.0,
                    help="largest axial and lateral colour (first-order C_I, C_II) as a multiple of the "
                         "design's own relay's; inf for no limit (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=1, help="seed of the random starts (default: %(default)s)")
    ap.add_argument("--write", action="store_true", help="write each best relay as a design file in --out")
    args = ap.parse_args(argv)
    if args.starts < 1:
        ap.error(f"--starts {args.starts}: at least 1")
    if not args.colour_max > 0:
        ap.error(f"--colour-max {args.colour_max}: a positive number or inf")
    if not (args.clear_diameter > 0 and math.isfinite(args.clear_diameter)):
        ap.error(f"--clear-diameter {args.clear_diameter}: a positive number of mm")
    try:
        limits = [math.inf if v.strip().lower() == "none" else float(v) for v in args.track_limits.split(",")]
    except ValueError:
        ap.error(f"--track-limits {args.track_limits!r}: numbers in mm, comma separated, or 'none'")
    assignments = [parse_glasses(ap, a) for a in (args.glasses or [
        "N-LAK22,N-LAK22,N-LAK22,N-LAK22", "N-LASF31A,N-LASF31A,N-LASF31A,N-LASF31A"])]

    from lfsim.design.design import load
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    path = Path(args.design)
    try:
        raw = tomllib.loads(path.read_text())
        model = IniModel(load(path))
        lam = float(model.lam)
        ref, phis = read_relay(raw, lam, [model.state(k).as_dict()["tunable_power_diopters"]
                                          for k in range(len(model.depths))])
        track = float(package(model)["track_mm"])
        rays, marginal = bundle(path)
    except (OSError, tomllib.TOMLDecodeError, ValueError, KeyError) as e:
        msg = str(e) if str(e).startswith(str(path)) else f"{path}: {e}"
        print(f"relay_petzval.py: error: {msg}", file=sys.stderr)
        return 2
    short = [lim for lim in limits if not ref.length + (lim - track) > 0]
    if short:
        ap.error(f"--track-limits {args.track_limits!r}: {short[0]:g} mm leaves the relay no length (the rest "
                 f"of {path.name} takes {track - ref.length:.2f} mm of its {track:.2f} mm track)")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, best = [], {}
    print(f"{path.name}: relay Petzval sum {ref.petzval():.4f} /mm, relay length {ref.length:.2f} mm, "
          f"track {track:.2f} mm")
    for glasses, lim in itertools.product(assignments, sorted(limits)):
        rules = Rules(clear_diameter=args.clear_diameter, max_length=ref.length + (lim - track),
                      colour_max=args.colour_max)
        S = Search(ref, phis, rays, marginal, rules)
        warm = [best[glasses]] if glasses in best else []
        found = search(S, glasses, lam, args.starts, args.seed, warm=warm)
        if found is not None:
            best[glasses] = found[0]
        row = {"track_limit_mm": None if math.isinf(lim) else lim, "glasses": list(glasses),
               "clear_diameter_mm": args.clear_diameter, "starts": args.starts,
               "warm_started": bool(warm)}
        if found is None:
            row.update(field_curvature=None, feasible_runs=0)
            print(f"track <= {lim:g} mm, {','.join(glasses)}: no feasible relay in "
                  f"{args.starts + len(warm)} SLSQP run(s)")
        else:
            x, fc, nf, origin = found
            fc, nf = float(fc), int(nf)
            r = S._relay(x, np.array([float(lookup(g).index(lam)) for g in glasses]),
                         np.array([dispersion(g) for g in glasses]))
            P = r.petzval()
            face, tun = S.semi_diameters(x, r.n)
            powers, k = S.state_powers(x, r.n)
            semi = S.lens_semi_diameters(face)
            sums = seidel(r, x[18], S.marginal, S.chief)
            colour = sums[4:6] / S.seidel0[4:6]
            row.update(field_curvature=fc, petzval_per_mm=P, feasible_runs=nf, best_start=origin,
                       colour_ratio=colour.tolist(),
                       seidel=sums.tolist(), track_mm=track + r.length - ref.length,
                       relay_length_mm=r.length, gaps_mm=r.gaps.tolist(), c1=r.c1.tolist(), c2=r.c2.tolist(),
                       thickness_mm=r.t.tolist(), semi_diameter_mm=semi.tolist(),
                       lens_power_diopters=((r.n - 1.0) * (r.c1 - r.c2) * 1e3).tolist(),
                       tunable_power_diopters=(powers * 1e3).tolist(), tunable_footprint_mm=2.0 * tun)
            print(f"track <= {lim:g} mm, {','.join(glasses)}: field curvature {fc:.3f}, Petzval {P:.4f} /mm "
                  f"(track {row['track_mm']:.2f} mm, axial / lateral colour {colour[0]:.2f} / {colour[1]:.2f} "
                  f"of the design's relay, "
                  f"lens powers {', '.join(f'{v:.1f}' for v in row['lens_power_diopters'])} D; "
                  f"{nf} of {args.starts + len(warm)} runs feasible, best from the {origin} start)")
            if origin == "reference, unmoved":
                print("  (no start found a flatter relay than the design's own, re-glassed; more --starts may)")
            if args.write:
                tag = f"track{'none' if math.isinf(lim) else f'{lim:g}'}_{'-'.join(glasses)}"
                p = out / f"{tag}.toml"
                p.write_text(tomli_w.dumps(write_variant(raw, r, glasses, powers, ref.length, semi=semi)))
                row["design"] = str(p)
        rows.append(row)
    S0 = Search(ref, phis, rays, marginal, Rules())
    doc = {"design": str(path), "reference": {
        "field_curvature": S0.field_curvature(S0.start(ref.n), ref.n), "petzval_per_mm": ref.petzval(),
        "seidel": S0.seidel0.tolist(), "relay_length_mm": ref.length, "track_mm": track},
        "colour_max": args.colour_max, "rows": rows}
    (out / "relay_petzval.json").write_text(json.dumps(doc, indent=2))
    _plot(doc, out / "relay_petzval.png")
    written = [r["design"] for r in rows if "design" in r]
    print(f"wrote {', '.join([str(out / 'relay_petzval.json'), str(out / 'relay_petzval.png'), *written])}")
    return 0


def _plot(doc: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for glasses in sorted({tuple(r["glasses"]) for r in doc["rows"]}):
        pts = [(r["track_limit_mm"], r["field_curvature"]) for r in doc["rows"]
               if tuple(r["glasses"]) == glasses and r["field_curvature"] is not None
               and r["track_limit_mm"] is not None]
        if pts:
            ax.plot(*zip(*sorted(pts)), "o-", label=", ".join(glasses))
    ref = doc["reference"]
    ax.plot([ref["track_mm"]], [ref["field_curvature"]], "ks", label="the design's relay")
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("track limit (mm)")
    ax.set_ylabel("relay field curvature (the design's S_IV² = 1)")
    ax.set_title("Least field curvature of four singlets at the same first order", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
