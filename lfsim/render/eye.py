"""Eye-lens camera for retinal rendering: the Mitsuba sensor plugin ``lfsim_eye``.

The sensor renders what an eye sees, in the eye's own visual-field units, so
an image lines up with a display's field of view:

* **Eye frame** (``to_world`` maps it to the scene): origin at the centre of
  the (entrance) pupil, the eye looks along local −z, +x is the viewer's
  right, +y up (lfsim's viewing-window convention, see
  :mod:`lfsim.render`). Units: mm.
* **Image**: row 0 = top (+y), column 0 = viewer's left (−x): the picture as
  the viewer sees it, not the inverted retinal image. With
  ``mapping="angular"`` (default) film x, y are linear in the per-axis visual
  angles ``θx = atan(dx/−dz)``, ``θy = atan(dy/−dz)`` of a direction d
  (degrees of visual field across ``fov_x`` × ``fov_y``); with
  ``mapping="tangent"`` they are linear in ``dx/−dz``, ``dy/−dz`` like a
  perspective camera.
* **Values**: radiance, averaged over the pupil (a uniform scene of radiance
  L renders as L).

Models (``model``):

``"ideal"``
    A thin lens at the pupil. Estimator per pixel sample: a pupil point q
    uniform on the disk (concentric map of ``sample3``), the chief direction
    ``c = normalize(tan θx, tan θy, −1)``, the focus point
    ``P = focus_distance · c`` (a sphere of focus about the pupil centre,
    ``focus_surface="sphere"``, default) or ``P = focus_distance ·
    (tan θx, tan θy, −1)`` (a focal plane, ``focus_surface="plane"``, as
    Mitsuba's ``thinlens``); the ray goes from q toward P (parallel to c for
    ``focus_distance = inf``). Weight 1, so the pixel value is
    ``E_q[L(q → P)]``, the pupil-averaged radiance.

``"arizona"``
    The Arizona eye (:mod:`lfsim.render.eye_models`), traced by lfsim's
    :class:`~lfsim.optics.tracer.SequentialTracer` (float32) inside the
    Mitsuba kernel. A pixel angle maps to the retinal point where the real
    chief ray of that object direction (through the iris centre) lands on
    the curved retina (numpy-precomputed table vs field angle, linearly
    interpolated in Dr.Jit). From that retinal point Q a point E is sampled
    uniformly on a disk of the paraxial exit-pupil plane that contains the
    real exit pupil for that field (centre and radius ``k(α)·ρ`` tabulated by
    bisecting the iris edge, ρ = paraxial exit-pupil radius); the ray Q → E is
    traced backwards through lens, iris (stop, a clear aperture on the
    anterior lens surface), aqueous and cornea into air. Estimator::

        I(pixel) = E_E[ k(α)² · 1{ray passes the iris} · L(ray leaving the cornea) ]

    i.e. the radiance averaged over the real pupil, normalized by the area
    of the paraxial exit pupil (the disk area ratio is k²). Paraxially,
    uniform points on the exit pupil are uniform points on the entrance
    pupil, so this is the ideal eye's estimator with the real eye's rays:
    a uniform scene renders as L times (real / paraxial pupil area), 1 within
    ~1 % over ±45°. The relative illumination of the curved retina
    (cos-power falloff) is deliberately not applied, as for the ideal eye.
    Rays that fail (vignetted by the iris, TIR, missed surface) get weight 0.
    ``pupil_diameter`` is the entrance-pupil diameter; the iris is sized so
    that its paraxial image through the cornea has that diameter. The
    eye-frame origin is the A = 0 entrance-pupil centre (≈ 2.96 mm behind
    the cornea vertex at 550 nm); rays leave from the cornea, so keep scene
    geometry > 3.1 mm in front of the origin.

Plugin properties: ``to_world``, ``film``, ``sampler``, ``model``
("ideal" | "arizona"), ``pupil_diameter`` (mm, default 3), ``focus_distance``
(mm from the origin, default inf = relaxed / 0 D), ``fov_x`` (deg, default
40), ``fov_y`` (deg; default: square pixels in the mapping's units),
``mapping`` ("angular" | "tangent"), ``focus_surface`` ("sphere" | "plane",
ideal only), ``accommodation`` (D, arizona only; default: solved from
``focus_distance`` with :func:`solve_accommodation`), ``wavelength_nm``
(default 550; arizona media dispersion, ignored by the ideal eye), ``wavelengths``
(spectral rendering, :mod:`lfsim.render.spectra`: comma-separated node wavelengths, each
ray picks one from its wavelength sample; the Arizona eye traces it there), ``diffraction``
(bool, default false: each ray turned by an angle sampled from the pupil's Airy pattern at
its wavelength, :mod:`lfsim.render.diffraction`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..backend import from_numpy
from . import mitsuba as _mitsuba
from .eye_models import (  # re-exported API
    arizona_first_order,
    axial_rms_spot,
    chief_ray_table,
    eye_origin_depth,
    iris_radius,
    paraxial_accommodation,
    pupil_table,
    solve_accommodation,
)

PLUGIN_NAME = "lfsim_eye"
MODELS = ("ideal", "arizona")
MAPPINGS = ("angular", "tangent")
FOCUS_SURFACES = ("sphere", "plane")

__all__ = ["EyeSpec", "register", "validate", "default_fov_y", "max_field_angle",
           "solve_accommodation", "paraxial_accommodation", "axial_rms_spot",
           "arizona_first_order", "chief_ray_table", "pupil_table", "iris_radius",
           "eye_origin_depth", "PLUGIN_NAME", "MODELS", "MAPPINGS", "FOCUS_SURFACES"]


# ------------------------------------------------------------------ checks
def _bad(key, value, allowed):
    return ValueError(f"eye {key}={value!r}: {allowed}")


def _number(key, value, *, positive=False, nonneg=False, allow_inf=False, upper=None):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise _bad(key, value, "must be a number")
    v = float(value)
    if math.isnan(v) or (math.isinf(v) and not (allow_inf and v > 0)):
        raise _bad(key, value, "must be a finite number" + (" or inf" if allow_inf else ""))
    if positive and not v > 0:
        raise _bad(key, value, "must be > 0")
    if nonneg and v < 0:
        raise _bad(key, value, "must be >= 0")
    if upper is not None and not v < upper:
        raise _bad(key, value, f"must be < {upper:g}")
    return v


def validate(model="ideal", pupil_diameter=3.0, focus_distance=math.inf, fov_x=40.0, fov_y=30.0,
             mapping="angular", focus_surface="sphere", accommodation=None,
             wavelength_nm=550.0) -> dict:
    """Check eye parameters; return them normalized (floats) or raise ValueError naming the key."""
    if model not in MODELS:
        raise _bad("model", model, f"allowed {', '.join(map(repr, MODELS))}")
    if mapping not in MAPPINGS:
        raise _bad("mapping", mapping, f"allowed {', '.join(map(repr, MAPPINGS))}")
    if focus_surface not in FOCUS_SURFACES:
        raise _bad("focus_surface", focus_surface, f"allowed {', '.join(map(repr, FOCUS_SURFACES))}")
    out = dict(model=model, mapping=mapping, focus_surface=focus_surface)
    out["pupil_diameter"] = _number("pupil_diameter", pupil_diameter, positive=True)
    out["focus_distance"] = _number("focus_distance", focus_distance, positive=True, allow_inf=True)
    out["fov_x"] = _number("fov_x", fov_x, positive=True, upper=180.0)
    out["fov_y"] = _number("fov_y", fov_y, positive=True, upper=180.0)
    out["wavelength_nm"] = _number("wavelength_nm", wavelength_nm, positive=True)
    if accommodation is not None:
        if model != "arizona":
            raise _bad("accommodation", accommodation, "only for model='arizona'")
        out["accommodation"] = _number("accommodation", accommodation)
    else:
        out["accommodation"] = None
    if model == "arizona" and focus_surface != "sphere":
        raise _bad("focus_surface", focus_surface, "only for model='ideal'")
    return out


def default_fov_y(fov_x: float, width: int, height: int, mapping: str) -> float:
    """Vertical extent giving square pixels in the mapping's units."""
    if mapping == "angular":
        return fov_x * height / width
    return 2.0 * math.degrees(math.atan(math.tan(math.radians(fov_x) / 2.0) * height / width))


def max_field_angle(fov_x: float, fov_y: float) -> float:
    """Largest angle (rad) from the axis of any pixel direction (the image corners)."""
    tx = math.tan(math.radians(fov_x) / 2.0)
    ty = math.tan(math.radians(fov_y) / 2.0)
    return math.atan(math.hypot(tx, ty))


# ------------------------------------------------------------------ plugin
_classes: dict[str, type] = {}


def _sensor_class(mi):
    """The ``mi.Sensor`` subclass for the current variant (built once per variant)."""
    import drjit as dr

    variant = mi.variant()
    if variant in _classes:
        return _classes[variant]

    class EyeSensor(mi.Sensor):
        """Mitsuba sensor ``lfsim_eye``; see :mod:`lfsim.render.eye`."""

        def __init__(self, props):
            mi.Sensor.__init__(self, props)
            film_size = self.film().size()
            mapping = props.get("mapping", "angular")
            fov_x = props.get("fov_x", 40.0)
            fov_y = props.get("fov_y", None)
            if fov_y is None:
                fov_y = default_fov_y(float(fov_x), film_size[0], film_size[1], mapping)
            p = validate(
                model=props.get("model", "ideal"),
                pupil_diameter=props.get("pupil_diameter", 3.0),
                focus_distance=props.get("focus_distance", math.inf),
                fov_x=fov_x, fov_y=fov_y, mapping=mapping,
                focus_surface=props.get("focus_surface", "sphere"),
                accommodation=props.get("accommodation", None),
                wavelength_nm=props.get("wavelength_nm", 550.0),
            )
            self.params = p
            self.model = p["model"]
            self.angular = p["mapping"] == "angular"
            self.half_fov = (math.radians(p["fov_x"]) / 2.0, math.radians(p["fov_y"]) / 2.0)
            self.tan_half = tuple(math.tan(h) for h in self.half_fov)
            self.pupil_radius = 0.5 * p["pupil_diameter"]
            self.focus = p["focus_distance"]
            # The same numbers as opaque scalars: a new focus distance, pupil, field
            # of view or film size reuses the compiled render kernel.
            op = lambda v: dr.opaque(mi.Float, float(v))  # noqa: E731
            self._half_fov = tuple(op(h) for h in self.half_fov)
            self._tan_half = tuple(op(t) for t in self.tan_half)
            self._pupil_radius = op(self.pupil_radius)
            self._focus = op(self.focus) if math.isfinite(self.focus) else None
            self.m_needs_sample_3 = True
            self.accommodation = None
            from .spectra import Wavelengths

            self.waves = Wavelengths.from_props(props)
            # Diffraction of the pupil (lfsim.render.diffraction): each ray turned by an angle
            # sampled from the pupil's Airy pattern at the ray's wavelength.
            self.diffraction = bool(props.get("diffraction", False))
            if self.diffraction:
                from .diffraction import AiryKick

                self._airy = AiryKick(mi)
                nm = self.waves.nm if self.waves is not None else (p["wavelength_nm"],)
                self._nodes_nm = from_numpy(mi.Float, np.asarray(nm, dtype=np.float32))
                dr.make_opaque(self._nodes_nm)
                self._pupil_diameter = op(p["pupil_diameter"])
            if self.model == "arizona":
                self._init_arizona(p)

        # -------------------------------------------------------- arizona setup
        def _init_arizona(self, p):
            from ..optics.tracer import SequentialTracer
            from .eye_models import arizona_reverse_system

            lam = p["wavelength_nm"]
            A = p["accommodation"]
            if A is None:
                A = solve_accommodation(p["focus_distance"], p["pupil_diameter"], lam)
            self.accommodation = float(A)
            fo = arizona_first_order(self.accommodation, lam)
            iris = iris_radius(p["pupil_diameter"], self.accommodation, lam)
            self.iris_radius = iris
            a_max = max_field_angle(p["fov_x"], p["fov_y"]) + math.radians(0.5)
            table = chief_ray_table(self.accommodation, lam, a_max)
            pupil = pupil_table(table, self.accommodation, lam, iris)
            self.table, self.pupil = table, pupil
            n = len(table.alpha)
            self.n_table = n
            self.inv_dalpha = dr.opaque(mi.Float, (n - 1) / a_max)
            self._last_row = dr.opaque(mi.Float, float(n - 2))
            # Packed per-field rows: retina r, reverse-frame z of the landing point,
            # exit-pupil disk centre (along the landing direction) and radius.
            z_lp = fo.z_lens_posterior
            # Spectral: the sampled disk 1% larger (its weight, the area ratio, with it), so
            # that it holds the real exit pupil at every wavelength node.
            grow = 1.0 if self.waves is None else 1.01
            cols = np.stack([table.r, z_lp - table.z, table.h_xp - pupil.offset * pupil.rho,
                             grow * pupil.k * pupil.rho, (grow * pupil.k) ** 2], axis=1)
            self.table_data = mi.Float(cols.ravel().astype(np.float32))
            dr.make_opaque(self.table_data)
            self.z_xp_rev = dr.opaque(mi.Float, float(z_lp - table.z_xp))
            self.z_lp_eye = dr.opaque(mi.Float, float(z_lp - eye_origin_depth(lam)))
            self.tracer = SequentialTracer(arizona_reverse_system(self.accommodation, iris), "float32")
            # Spectral: one parameter block per wavelength node (ocular media dispersion); the
            # retina, its pixel mapping and the exit-pupil disk stay the reference
            # wavelength's: the retina does not move with colour, the image does.
            self.P = self.tracer.params(lam if self.waves is None else list(self.waves.nm))

        # -------------------------------------------------------- film → angles
        def _tangents(self, s2, du=0.0, dv=0.0):
            """Per-axis tangents (tx, ty) of the pixel direction at film sample ``s2``."""
            film = self.film()
            size, crop, off = film.size(), film.crop_size(), film.crop_offset()
            op = lambda v: dr.opaque(mi.Float, float(v))  # noqa: E731
            # × the reciprocal: what a division by the literal size compiled to.
            u = (op(off[0]) + s2.x * op(crop[0])) * op(1.0 / size[0])
            v = (op(off[1]) + s2.y * op(crop[1])) * op(1.0 / size[1])
            if du:
                u = u + op(du)
            if dv:
                v = v + op(dv)
            if self.angular:
                tx = dr.tan((2.0 * u - 1.0) * self._half_fov[0])
                ty = dr.tan((1.0 - 2.0 * v) * self._half_fov[1])
            else:
                tx = (2.0 * u - 1.0) * self._tan_half[0]
                ty = (1.0 - 2.0 * v) * self._tan_half[1]
            return tx, ty

        def _pixel_step(self):
            size = self.film().size()
            return 1.0 / size[0], 1.0 / size[1]

        # -------------------------------------------------------------- ideal
        def _ideal_dir(self, q, tx, ty):
            if math.isinf(self.focus):
                return dr.normalize(mi.Vector3f(tx, ty, -1.0))
            if self.params["focus_surface"] == "sphere":
                P = dr.normalize(mi.Vector3f(tx, ty, -1.0)) * self._focus
            else:
                P = mi.Vector3f(tx, ty, -1.0) * self._focus
            return dr.normalize(mi.Vector3f(P.x - q.x, P.y - q.y, P.z))

        def _sample_ideal(self, s2, s3, differentials):
            tx, ty = self._tangents(s2)
            q = mi.warp.square_to_uniform_disk_concentric(s3) * self._pupil_radius
            o = mi.Point3f(q.x, q.y, 0.0)
            d = self._ideal_dir(q, tx, ty)
            ok = d.z < 0.0
            w = mi.Float(1.0)
            diffs = None
            if differentials:
                hx, hy = self._pixel_step()
                diffs = (self._ideal_dir(q, *self._tangents(s2, du=hx)),
                         self._ideal_dir(q, *self._tangents(s2, dv=hy)))
            return o, d, w, ok, diffs

        # ------------------------------------------------------------ arizona
        def _lookup(self, alpha):
            x = alpha * self.inv_dalpha
            i = mi.UInt32(dr.clip(dr.floor(x), 0.0, self._last_row))
            f = dr.clip(x - mi.Float(i), 0.0, 1.0)
            ncol = 5
            out = []
            for c in range(ncol):
                a = dr.gather(mi.Float, self.table_data, i * ncol + c)
                b = dr.gather(mi.Float, self.table_data, (i + 1) * ncol + c)
                out.append(dr.fma(f, b - a, a))
            return out

        def node(self, time):
            """Wavelength node (UInt32) of each ray (0 when monochrome).

            Mitsuba's RGB integrators pass no wavelength sample (``sample1`` is 0), but they
            draw a time sample when the shutter is open for a while: a spectral eye opens
            it over [0, 1) (:meth:`EyeSpec.sensor_dict`; the scene is static, so time is
            free), and the time is the ray's wavelength sample.
            """
            from .spectra import node_index

            if self.waves is None:
                return node_index(mi, time, 1)
            u = (time - self.shutter_open()) * (1.0 / max(self.shutter_open_time(), 1e-30))
            return node_index(mi, u, self.waves.count)

        def _sample_arizona(self, s2, s3, differentials, j):
            from ..optics.tracer import RayState

            T = self.tracer.T
            tx, ty = self._tangents(s2)
            rho2 = dr.fma(tx, tx, ty * ty)
            hyp = dr.sqrt(rho2)
            alpha = dr.atan(hyp)
            nz = hyp > 0.0
            inv = 1.0 / dr.select(nz, hyp, 1.0)
            ux = dr.select(nz, tx * inv, 1.0)
            uy = dr.select(nz, ty * inv, 0.0)
            r, zq, hc, rad, weight = self._lookup(alpha)
            # Reverse frame: (x, y)_rev = (−x, y)_eye; the landing point is at
            # −r·u in the eye frame, i.e. r·(ux, −uy) in the reverse frame.
            wx, wy = ux, -uy
            disk = mi.warp.square_to_uniform_disk_concentric(s3)
            ex = dr.fma(disk.x, rad, hc * wx)
            ey = dr.fma(disk.y, rad, hc * wy)
            qx, qy = r * wx, r * wy
            origin = T.Array3(qx, qy, zq)
            direction = T.Array3(ex - qx, ey - qy, self.z_xp_rev - zq)
            n = dr.width(origin)
            out = self.tracer.trace(self.P, RayState(origin, direction),
                                    block=dr.zeros(T.UInt32, n) if self.waves is None else T.UInt32(j),
                                    clip=True)
            ok = (out.status == 0) & (out.d.z > 0.0)
            chief = dr.normalize(mi.Vector3f(tx, ty, -1.0))
            o = mi.Point3f(dr.select(ok, -out.p.x, 0.0), dr.select(ok, out.p.y, 0.0),
                           dr.select(ok, self.z_lp_eye - out.p.z, 0.0))
            d = mi.Vector3f(dr.select(ok, -out.d.x, chief.x), dr.select(ok, out.d.y, chief.y),
                            dr.select(ok, -out.d.z, chief.z))
            diffs = None
            if differentials:
                # Approximate differentials: the ray turned by the chief-ray change
                # over one pixel (texture filtering only; not used for transport).
                hx, hy = self._pixel_step()
                cx = dr.normalize(mi.Vector3f(*self._tangents(s2, du=hx), -1.0))
                cy = dr.normalize(mi.Vector3f(*self._tangents(s2, dv=hy), -1.0))
                diffs = (dr.normalize(d + (cx - chief)), dr.normalize(d + (cy - chief)))
            return o, d, weight, ok, diffs

        # --------------------------------------------------------- interface
        def _sample(self, time, sample1, s2, s3, active, differentials):
            j = self.node(time)
            if self.model == "ideal":
                o, d, w, ok, diffs = self._sample_ideal(s2, s3, differentials)
            else:
                o, d, w, ok, diffs = self._sample_arizona(s2, s3, differentials, j)
            if self.diffraction:
                from .diffraction import kick_samples

                u1, u2 = kick_samples(mi, self, s2, s3, active)
                lam = dr.gather(mi.Float, self._nodes_nm, j)
                d = self._airy.kick(d, u1, u2, lam, self._pupil_diameter)
            ok = ok & active
            to_world = self.m_to_world
            wavelengths = dr.zeros(mi.Color0f) if not mi.is_spectral else None
            weight = mi.Spectrum(dr.select(ok, w, 0.0))
            if mi.is_spectral:
                wavelengths, wav_w = self.sample_wavelengths(
                    dr.zeros(mi.SurfaceInteraction3f), sample1, active)
                weight = weight * wav_w
            o_w = to_world @ o
            d_w = dr.normalize(to_world @ d)
            if not differentials:
                return mi.Ray3f(o_w, d_w, time, wavelengths), weight
            ray = mi.RayDifferential3f(o_w, d_w, time, wavelengths)
            ray.o_x = o_w
            ray.o_y = o_w
            ray.d_x = dr.normalize(to_world @ diffs[0])
            ray.d_y = dr.normalize(to_world @ diffs[1])
            ray.has_differentials = True
            return ray, weight

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            return self._sample(time, sample1, sample2, sample3, active, False)

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            return self._sample(time, sample1, sample2, sample3, active, True)

        def to_string(self):
            p = self.params
            extra = (f", accommodation={self.accommodation:.4f} D"
                     if self.accommodation is not None else "")
            return (f"EyeSensor[model={p['model']}, pupil={p['pupil_diameter']} mm, "
                    f"focus={p['focus_distance']} mm, fov=({p['fov_x']}, {p['fov_y']}) deg, "
                    f"mapping={p['mapping']}{extra}]")

    _classes[variant] = EyeSensor
    return EyeSensor


_registered: set[str] = set()


def register():
    """Register the ``lfsim_eye`` sensor plugin for lfsim's Mitsuba variant (idempotent).

    Returns the ``mitsuba`` module.
    """
    mi = _mitsuba()
    variant = mi.variant()
    if variant not in _registered:
        cls = _sensor_class(mi)
        mi.register_sensor(PLUGIN_NAME, lambda props: cls(props))
        _registered.add(variant)
    return mi


# --------------------------------------------------------------- plain API
def sampler_type(spp: int) -> str:
    """The retinal cameras' sampler: ``lfsim_sobol`` (:mod:`lfsim.render.sobol`), Owen-scrambled
    Sobol points jointly over film position, pupil point, wavelength and diffraction, for any
    ``spp`` (registered here).

    Measured on the default focal stack's display image (RMSE / mean of one image, from two
    seeds): 0.040 at 64 spp and 0.018 at 256 spp, against 0.047 and 0.0225 with Mitsuba's
    ``multijitter`` and 0.084 with ``independent`` at 64 spp; 0.022 at 64 spp without
    diffraction, against 0.034 (docs/rendering.md, ``lfsim report accuracy``).
    """
    from .sobol import PLUGIN_NAME, register

    register()
    return PLUGIN_NAME


@dataclass(frozen=True)
class EyeSpec:
    """A retinal camera in plain Python (units: mm, degrees, diopters, nm).

    Attributes
    ----------
    model : {"ideal", "arizona"}
    pupil_diameter_mm : float
        Entrance-pupil diameter.
    focus_mm : float
        Distance the eye focuses at, from the pupil (inf = relaxed, 0 D).
        For the Arizona eye it fixes the accommodation through
        :func:`solve_accommodation` unless ``accommodation_diopters`` is given.
    fov_deg : (float, float)
        Full image extent (x, y) in degrees.
    resolution : (int, int)
        Image (width, height) in pixels.
    accommodation_diopters : float or None
        Arizona eye only: accommodation parameter A, overriding ``focus_mm``.
    wavelength_nm : float
        Arizona eye media wavelength (default 550 nm).
    mapping : {"angular", "tangent"}
    focus_surface : {"sphere", "plane"}
        Ideal eye only.
    rfilter : str
        Mitsuba reconstruction filter of the film (default "box").
    wavelengths : lfsim.render.spectra.Wavelengths or None
        Spectral rendering: the wavelength nodes the rays are spread over (one render
        pass; None: ``wavelength_nm``). The Arizona eye traces each ray at its node;
        ``wavelength_nm`` stays the reference of its accommodation, retina mapping
        and pupil.
    diffraction : bool
        Diffraction of the pupil: each ray turned by an angle sampled from the pupil's Airy
        pattern at its wavelength (:mod:`lfsim.render.diffraction`).
    """

    model: str = "ideal"
    pupil_diameter_mm: float = 3.0
    focus_mm: float = math.inf
    fov_deg: tuple[float, float] = (40.0, 30.0)
    resolution: tuple[int, int] = (160, 120)
    accommodation_diopters: float | None = None
    wavelength_nm: float = 550.0
    mapping: str = "angular"
    focus_surface: str = "sphere"
    rfilter: str = "box"
    wavelengths: object = None
    diffraction: bool = False

    def __post_init__(self):
        try:
            fx, fy = self.fov_deg
        except (TypeError, ValueError):
            raise _bad("fov_deg", self.fov_deg, "must be a pair (x, y) of degrees") from None
        try:
            w, h = self.resolution
        except (TypeError, ValueError):
            raise _bad("resolution", self.resolution, "must be a pair (width, height)") from None
        for key, v in (("resolution", w), ("resolution", h)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise _bad(key, self.resolution, "must be two integers >= 1")
        try:
            validate(self.model, self.pupil_diameter_mm, self.focus_mm, fx, fy, self.mapping,
                     self.focus_surface, self.accommodation_diopters, self.wavelength_nm)
        except ValueError as e:
            # Name the dataclass field rather than the plugin property.
            msg = str(e)
            for prop, field in (("pupil_diameter=", "pupil_diameter_mm="),
                                ("focus_distance=", "focus_mm="), ("fov_x=", "fov_deg[0]="),
                                ("fov_y=", "fov_deg[1]="),
                                ("accommodation=", "accommodation_diopters=")):
                msg = msg.replace(f"eye {prop}", f"eye {field}")
            raise ValueError(msg) from None
        if not isinstance(self.rfilter, str) or not self.rfilter:
            raise _bad("rfilter", self.rfilter, "must be a Mitsuba filter name")

    def accommodation(self) -> float | None:
        """Accommodation A (D) the Arizona eye will use (None for the ideal eye)."""
        if self.model != "arizona":
            return None
        if self.accommodation_diopters is not None:
            return float(self.accommodation_diopters)
        return solve_accommodation(float(self.focus_mm), float(self.pupil_diameter_mm),
                                   float(self.wavelength_nm))

    def sensor_dict(self, to_world=None, spp: int = 16, seed: int = 0) -> dict:
        """The Mitsuba dict of this eye for ``mi.load_dict`` (registers the plugin).

        ``to_world``: eye frame → scene, a ``mi.ScalarTransform4f``, a 4×4
        array, or None (identity: the eye at the origin looking along −z).
        """
        mi = register()
        if isinstance(spp, bool) or not isinstance(spp, (int, np.integer)) or spp < 1:
            raise _bad("spp", spp, "must be an integer >= 1")
        if to_world is None:
            T = mi.ScalarTransform4f()
        elif isinstance(to_world, (mi.ScalarTransform4f, getattr(mi, "ScalarAffineTransform4f", ()))):
            T = to_world
        else:
            m = np.asarray(to_world, dtype=np.float64)
            if m.shape != (4, 4) or not np.all(np.isfinite(m)):
                raise _bad("to_world", to_world, "must be a 4x4 finite matrix or a Mitsuba transform")
            T = mi.ScalarTransform4f(m.tolist())
        w, h = self.resolution
        d = {
            "type": PLUGIN_NAME,
            "to_world": T,
            "model": self.model,
            "pupil_diameter": float(self.pupil_diameter_mm),
            "focus_distance": float(self.focus_mm),
            "fov_x": float(self.fov_deg[0]),
            "fov_y": float(self.fov_deg[1]),
            "mapping": self.mapping,
            "wavelength_nm": float(self.wavelength_nm),
            "film": {"type": "hdrfilm", "width": int(w), "height": int(h),
                     "pixel_format": "rgb", "rfilter": {"type": self.rfilter}},
            "sampler": {"type": sampler_type(int(spp)), "sample_count": int(spp), "seed": int(seed)},
        }
        if self.model == "ideal":
            d["focus_surface"] = self.focus_surface
        if self.accommodation_diopters is not None:
            d["accommodation"] = float(self.accommodation_diopters)
        if self.diffraction:
            d["diffraction"] = True
        if self.wavelengths is not None:
            d.update(self.wavelengths.props())
            if self.wavelengths.count > 1:  # the time sample carries the wavelength sample
                d["shutter_open"], d["shutter_close"] = 0.0, 1.0
        return d

    def load(self, to_world=None, spp: int = 16, seed: int = 0):
        """``mi.load_dict(self.sensor_dict(...))``: the sensor object."""
        mi = register()
        return mi.load_dict(self.sensor_dict(to_world, spp, seed))
