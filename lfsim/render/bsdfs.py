"""Mitsuba BSDFs for sequential optics: a noise-free dielectric interface and
an ideal thin lens (the tracer's paraxial surface).

Both are delta BSDFs (``eval``/``pdf`` are zero; only ``sample`` matters) and
work for light arriving from either side. Register them with
:func:`register` (idempotent) before loading a scene that names them;
:mod:`lfsim.render.optics_scene` does so.

``lfsim_interface``
    Properties ``int_ior`` and ``ext_ior`` (floats; ``ext_ior`` is the index
    on the side the shading normal points to, as in Mitsuba's ``dielectric``).
    Always refracts (Snell's law, no Fresnel branch, so no sampling noise)
    and reflects, with weight 1, only under total internal reflection. The
    refraction weight is 1 by default, or the Fresnel transmittance 1 − F
    (unpolarized, ``mi.fresnel``) with ``fresnel = true``, which makes the
    image depend on the indices through the transmission loss too. Both
    indices are differentiable parameters (``mi.traverse`` keys
    ``….bsdf.int_ior`` / ``….bsdf.ext_ior``). The radiance scaling by η² of
    a real interface is left out: it cancels on any path that enters and
    leaves the same medium.

``lfsim_thinlens``
    Ideal thin lens of power ``power`` (1/mm) in a medium of index ``ior``,
    or an M × N array of them (``array_m``, ``array_n``, ``pitch_x``,
    ``pitch_y``, ``center_x``, ``center_y``). It needs the surface-local
    (x, y) of the hit in the shape's UVs (lfsim's meshes store them) and the
    local axes in ``rotation`` (a string of 9 numbers, the row-major matrix
    whose columns are the surface's local x, y, z axes in world space).
    Deflection as :func:`lfsim.optics.tracer._ideal_lens`: along the
    propagation direction ``tan θ' = tan θ − h·φ/n`` in x and y, with h the
    hit relative to the lens (lenslet) centre. The map is reciprocal, so the
    same rule serves camera paths and light paths. ``power`` is
    differentiable. A hit outside the array's cells is absorbed.
"""

from __future__ import annotations

import numpy as np

from . import mitsuba

INTERFACE = "lfsim_interface"
THINLENS = "lfsim_thinlens"

_registered: set[tuple[str, str]] = set()


def _classes(mi, dr):
    """Define the plugin classes for the current variant."""

    delta_t = mi.BSDFFlags.DeltaTransmission
    delta_r = mi.BSDFFlags.DeltaReflection
    sides = mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide

    class DeltaBSDF(mi.BSDF):
        """Purely specular: nothing to evaluate, only to sample."""

        def eval(self, ctx, si, wo, active=True):
            return mi.Color3f(0.0)

        def pdf(self, ctx, si, wo, active=True):
            return mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return mi.Color3f(0.0), mi.Float(0.0)

        def parameters_changed(self, keys):
            pass

    class InterfaceBSDF(DeltaBSDF):
        """Dielectric interface: refraction with weight 1 (or 1 − F), reflection only on TIR."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.int_ior = mi.Float(props.get("int_ior", 1.5046))
            self.ext_ior = mi.Float(props.get("ext_ior", 1.0))
            self.fresnel = bool(props.get("fresnel", False))
            self.spec = {"type": INTERFACE, "int_ior": float(props.get("int_ior", 1.5046)),
                         "ext_ior": float(props.get("ext_ior", 1.0))}
            if self.fresnel:
                self.spec["fresnel"] = True
            self.m_components = [delta_r | sides, delta_t | sides]
            self.m_flags = delta_r | delta_t | sides

        def sample(self, ctx, si, sample1, sample2, active=True):
            wi = si.wi
            cos_i = mi.Frame3f.cos_theta(wi)
            outside = cos_i >= 0.0
            # eta = n_t / n_i for the side the ray comes from.
            eta = dr.select(outside, self.int_ior / self.ext_ior, self.ext_ior / self.int_ior)
            inv = dr.rcp(eta)
            sin2_t = inv * inv * dr.maximum(1.0 - cos_i * cos_i, 0.0)
            tir = sin2_t >= 1.0
            cos_t = dr.sqrt(dr.maximum(1.0 - sin2_t, 0.0))
            cos_t = dr.select(outside, -cos_t, cos_t)
            wo_t = mi.Vector3f(-wi.x * inv, -wi.y * inv, cos_t)
            wo_r = mi.Vector3f(-wi.x, -wi.y, wi.z)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = dr.select(tir, wo_r, wo_t)
            bs.pdf = mi.Float(1.0)
            bs.eta = dr.select(tir, 1.0, eta)
            bs.sampled_type = dr.select(tir, mi.UInt32(+delta_r), mi.UInt32(+delta_t))
            bs.sampled_component = dr.select(tir, mi.UInt32(0), mi.UInt32(1))
            w = mi.Float(1.0)
            if self.fresnel:
                # mi.fresnel takes eta = n_int / n_ext and the cosine on the ext side's sign.
                F, _, _, _ = mi.fresnel(cos_i, self.int_ior / self.ext_ior)
                w = dr.select(tir, 1.0, 1.0 - F)
            return bs, dr.select(active, mi.Color3f(w), mi.Color3f(0.0))

        def traverse(self, cb):
            cb.put("int_ior", self.int_ior, mi.ParamFlags.Differentiable)
            cb.put("ext_ior", self.ext_ior, mi.ParamFlags.Differentiable)

        def to_string(self):
            return (f"InterfaceBSDF[int_ior={self.spec['int_ior']}, ext_ior={self.spec['ext_ior']}, "
                    f"fresnel={self.fresnel}]")

    class ThinLensBSDF(DeltaBSDF):
        """Ideal thin lens (array) on a plane whose UVs are the local (x, y)."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            power = float(props.get("power", 0.0))
            ior = float(props.get("ior", 1.0))
            rot = props.get("rotation", "1 0 0 0 1 0 0 0 1")
            am, an = int(props.get("array_m", 1)), int(props.get("array_n", 1))
            px, py = float(props.get("pitch_x", 1.0)), float(props.get("pitch_y", 1.0))
            cx, cy = float(props.get("center_x", 0.0)), float(props.get("center_y", 0.0))
            R = np.array([float(v) for v in str(rot).split()], dtype=np.float64).reshape(3, 3)
            self.spec = {"type": THINLENS, "power": power, "ior": ior, "rotation": str(rot),
                         "array_m": am, "array_n": an, "pitch_x": px, "pitch_y": py,
                         "center_x": cx, "center_y": cy}
            self.power = mi.Float(power)
            self.ior = mi.Float(ior)
            self.ex, self.ey, self.ez = (mi.ScalarVector3f(*R[:, k].tolist()) for k in range(3))
            self.am, self.an, self.px, self.py, self.cx, self.cy = am, an, px, py, cx, cy
            self.m_components = [delta_t | sides]
            self.m_flags = delta_t | sides

        def _lens_centre(self, uv):
            x, y = uv.x, uv.y
            if self.am == 1 and self.an == 1:
                return mi.Float(0.0), mi.Float(0.0), mi.Bool(True)
            m = mi.Int32(dr.floor((x - self.cx) / self.px + 0.5 * self.am))
            n = mi.Int32(dr.floor((y - self.cy) / self.py + 0.5 * self.an))
            ok = (m >= 0) & (m < self.am) & (n >= 0) & (n < self.an)
            xm = self.cx + (mi.Float(m) - 0.5 * (self.am - 1)) * self.px
            yn = self.cy + (mi.Float(n) - 0.5 * (self.an - 1)) * self.py
            return xm, yn, ok

        def sample(self, ctx, si, sample1, sample2, active=True):
            # Propagation direction (toward the surface) in the surface's local frame.
            w = -si.to_world(si.wi)
            d = mi.Vector3f(dr.dot(self.ex, w), dr.dot(self.ey, w), dr.dot(self.ez, w))
            xm, yn, ok = self._lens_centre(si.uv)
            hx, hy = si.uv.x - xm, si.uv.y - yn
            adz = dr.abs(d.z)
            inv = dr.rcp(dr.select(adz > 0.0, adz, 1.0))
            k = self.power / self.ior
            t = mi.Vector3f(d.x * inv - hx * k, d.y * inv - hy * k, dr.sign(d.z))
            t = dr.normalize(t)
            wo = si.to_local(self.ex * t.x + self.ey * t.y + self.ez * t.z)
            bs = dr.zeros(mi.BSDFSample3f)
            bs.wo = wo
            bs.pdf = mi.Float(1.0)
            bs.eta = mi.Float(1.0)
            bs.sampled_type = mi.UInt32(+delta_t)
            bs.sampled_component = mi.UInt32(0)
            good = active & ok & (adz > 0.0)
            return bs, dr.select(good, mi.Color3f(1.0), mi.Color3f(0.0))

        def traverse(self, cb):
            cb.put("power", self.power, mi.ParamFlags.Differentiable)
            cb.put("ior", self.ior, mi.ParamFlags.Differentiable)

        def to_string(self):
            return f"ThinLensBSDF[power={self.spec['power']}, array={self.am}x{self.an}]"

    return InterfaceBSDF, ThinLensBSDF


def register():
    """Register ``lfsim_interface`` and ``lfsim_thinlens`` for the current variant (idempotent)."""
    mi = mitsuba()
    import drjit as dr

    key = mi.variant()
    if (key, "bsdfs") in _registered:
        return mi
    interface, thinlens = _classes(mi, dr)
    mi.register_bsdf(INTERFACE, lambda props: interface(props))
    mi.register_bsdf(THINLENS, lambda props: thinlens(props))
    _registered.add((key, "bsdfs"))
    return mi


def interface(int_ior: float, ext_ior: float, fresnel: bool = False) -> dict:
    """Scene dict of an ``lfsim_interface`` BSDF (``ext_ior`` on the normal's side;
    ``fresnel``: refraction weight 1 − F instead of 1)."""
    out = {"type": INTERFACE, "int_ior": float(int_ior), "ext_ior": float(ext_ior)}
    if fresnel:
        out["fresnel"] = True
    return out


def thin_lens(power: float, ior: float, rotation: np.ndarray, array=None) -> dict:
    """Scene dict of an ``lfsim_thinlens`` BSDF.

    ``rotation``: 3×3 local→world matrix of the surface; ``array``: optional
    ``(M, N, (pitch_x, pitch_y), (center_x, center_y))``.
    """
    R = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
    out = {"type": THINLENS, "power": float(power), "ior": float(ior),
           "rotation": " ".join(repr(float(v)) for v in R.ravel())}
    if array is not None:
        m, n, (px, py), (cx, cy) = array
        out.update(array_m=int(m), array_n=int(n), pitch_x=float(px), pitch_y=float(py),
                   center_x=float(cx), center_y=float(cy))
    return out


def mirror() -> dict:
    """A perfect two-sided mirror (reflectance 1)."""
    return {"type": "twosided", "bsdf": {"type": "conductor", "material": "none"}}


def absorber() -> dict:
    """A black surface (rims, walls, masks): absorbs every ray, both sides."""
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
