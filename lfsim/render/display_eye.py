"""The eye looking through the exact design at the display (the analytic path).

Sensor plugin ``lfsim_display_eye``: an :mod:`lfsim.render.eye` camera whose
rays, leaving the pupil on the viewing window, are traced backwards through the
design by :class:`~lfsim.render.analytic.ReverseOptics` inside ``sample_ray``.
The ray handed to Mitsuba starts just in front of the display plane and points
at it, so the scene holds nothing but the display emitter: no optics meshes,
no relay, no prism — the scene leaves out what this path does not need.
Vignetted rays carry weight 0; the estimate is the eye's (pupil-averaged
radiance), so a display path and a natural view of the same eye compare
directly.
"""

from __future__ import annotations

import itertools

import drjit as dr

from ..backend import register_plugin

PLUGIN_NAME = "lfsim_display_eye"
#: ReverseOptics objects by id (Mitsuba properties hold only plain values).
_OPTICS: dict[str, object] = {}
_ids = itertools.count()
#: Distance (mm) in front of the display plane where the handed-over ray starts.
LAUNCH_GAP = 0.01


def attach(optics) -> str:
    """Make a :class:`ReverseOptics` available to sensors; returns its id."""
    key = f"optics{next(_ids)}"
    _OPTICS[key] = optics
    return key


def release(key: str) -> None:
    _OPTICS.pop(key, None)


def _sensor_class(mi):
    from .eye import register as register_eye

    register_eye()

    class DisplayEye(mi.Sensor):
        def __init__(self, props):
            eye = {"type": "lfsim_eye"}
            for name in ("model", "pupil_diameter", "focus_distance", "fov_x", "fov_y", "mapping",
                         "wavelength_nm", "focus_surface", "accommodation", "wavelengths",
                         "shutter_open", "shutter_close"):
                if name in props:
                    eye[name] = props[name]
            key = props["optics"]
            if key not in _OPTICS:
                raise ValueError(f"lfsim_display_eye: optics = {key!r}: no such optics attached")
            self.optics = _OPTICS[key]
            super().__init__(props)
            # The inner eye maps film samples to visual angles: it needs this film's size and
            # crop window (a cropped render is a window of the full image, not all of it).
            film = self.film()
            (w, h), (cw, ch), (ox, oy) = film.size(), film.crop_size(), film.crop_offset()
            eye["film"] = {"type": "hdrfilm", "width": int(w), "height": int(h), "crop_offset_x": int(ox),
                           "crop_offset_y": int(oy), "crop_width": int(cw), "crop_height": int(ch)}
            self.eye = mi.load_dict(eye)
            self.m_needs_sample_3 = True
            # Diffraction on the display path: each view's aperture (the lenslet stop clipped by
            # the pupil's image) at the stop, not the pupil again at the eye.
            self.diffraction = bool(props.get("diffraction", False))
            if self.diffraction:
                kd = self.optics.diffraction
                pupil = float(props.get("pupil_diameter", 3.0))
                if kd is None or abs(kd.pupil_mm - pupil) > 1e-9:
                    raise ValueError(f"lfsim_display_eye: diffraction needs optics built for the eye's "
                                     f"{pupil:g} mm pupil (ReverseOptics(diffraction_pupil_mm=...))")
            n_eye = 1 if self.eye.waves is None else self.eye.waves.count
            if n_eye != self.optics.wavelengths.count:
                raise ValueError(f"lfsim_display_eye: the eye has {n_eye} wavelength node(s), the optics "
                                 f"{self.optics.wavelengths.count}: build both from one Wavelengths")

        def _sample(self, time, sample1, sample2, sample3, active):
            ray, weight = self.eye.sample_ray(time, sample1, sample2, sample3, active)
            T = self.optics.T
            o = T.Array3(ray.o.x, ray.o.y, ray.o.z)
            d = T.Array3(ray.d.x, ray.d.y, ray.d.z)
            kick_u = None
            if self.diffraction:
                from .diffraction import kick_samples

                kick_u = kick_samples(mi, self, sample2, sample3, active, salt=0x5BD1E995)
            p, dd, ok = self.optics.to_display(o, d, block=self.eye.node(time), kick_u=kick_u)
            ok = ok & (dd.z < 0)
            start = p - LAUNCH_GAP * dd
            out = mi.Ray3f(mi.Point3f(start.x, start.y, start.z),
                           mi.Vector3f(dd.x, dd.y, dd.z), time, ray.wavelengths)
            return out, dr.select(ok & active, weight, 0.0)

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            return self._sample(time, sample1, sample2, sample3, active)

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            ray, w = self._sample(time, sample1, sample2, sample3, active)
            return mi.RayDifferential3f(ray), w

        def to_string(self):
            return f"DisplayEye[{self.eye}]"

    return DisplayEye


def register():
    """Register ``lfsim_display_eye`` (idempotent); returns the mitsuba module."""
    return register_plugin("sensor", PLUGIN_NAME, _sensor_class)


def sensor_dict(eye_spec, optics_key: str, spp: int, seed: int = 0) -> dict:
    """Mitsuba dict of the analytic display eye for an :class:`~lfsim.render.eye.EyeSpec`."""
    register()
    d = eye_spec.sensor_dict(None, spp, seed)
    d["type"] = PLUGIN_NAME
    d["optics"] = optics_key
    d.pop("to_world", None)
    return d
