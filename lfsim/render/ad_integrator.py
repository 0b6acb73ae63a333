"""A differentiable integrator for specular chains: eye → refractions / reflections → display.

Every interaction on lfsim's optics meshes is a delta BSDF (``lfsim_interface``,
``lfsim_thinlens``, mirrors) or an absorber, and the only light is the display
emitter. The radiance of a camera ray is then a deterministic product along
one path::

    L(ray) = Π_k w_k · L_e(x_n, −d_n)

with w_k the weight of the BSDF sample at the k-th surface (1, or 1 − F for
a Fresnel interface; 0 where the ray is absorbed) and L_e the display's
emitted radiance (a bilinear texture lookup at the hit's uv) where the chain
ends on it. :func:`specular_chain` unrolls ``ray_intersect → emitter eval →
bsdf.sample → spawn_ray`` in Python with gradients attached, so one AD graph
holds the whole chain: the derivative along a fixed sample (the *interior*
term) of every hit position, shading normal, index and texture lookup, in
forward and in reverse mode. Mitsuba's stock ``path`` (its derivative
through refraction chains came out silently wrong) and ``prb`` (about half
the value) are not used. Visibility changes (a ray switching lenslet cell,
vignetted or not) are *boundary* terms that this estimator does not contain
(:mod:`lfsim.render.gradcheck` measures them).

``lfsim_specular`` registers the same estimator as a Mitsuba integrator (an
``mi.ad.common.ADIntegrator``, so ``mi.render`` with ``params`` and
``dr.forward`` / ``dr.backward`` work on it).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr

from . import mitsuba

NAME = "lfsim_specular"
_registered: set[str] = set()


@dataclass
class Chain:
    """Per-sample result of :func:`specular_chain` (Mitsuba float32 arrays)."""

    L: object  # mi.Color3f radiance
    valid: object  # mi.Bool: the chain ended on an emitter
    p: object  # mi.Point3f: the emitter hit (0 where not valid)
    code: object  # mi.UInt32: hash of the sequence of shapes met
    depth: object  # mi.UInt32: number of surfaces met


def specular_chain(scene, ray, active=True, max_depth: int = 64) -> Chain:
    """Follow camera rays through delta interactions to an emitter, differentiably.

    Deterministic (BSDF sample values 0.5: every BSDF of the optics is a delta
    BSDF). A lane ends when it reaches an emitter (valid), misses everything,
    is absorbed (BSDF weight 0) or after ``max_depth`` surfaces. Failed lanes
    are parked with ``dr.select``, so no NaN reaches a value or a gradient.
    Call it with gradients enabled on the scene parameters (``mi.traverse``)
    or on the ray to differentiate.
    """
    mi = mitsuba()
    n = dr.width(ray.o)
    ctx = mi.BSDFContext()
    active = mi.Bool(active) & dr.full(mi.Bool, True, n)
    L = dr.zeros(mi.Color3f, n)
    beta = dr.full(mi.Color3f, 1.0, n)
    p_em = dr.zeros(mi.Point3f, n)
    valid = dr.full(mi.Bool, False, n)
    code = dr.zeros(mi.UInt32, n)
    depth = dr.zeros(mi.UInt32, n)
    for _ in range(int(max_depth)):
        si = scene.ray_intersect(ray, active)
        hit = active & si.is_valid()
        emitter = si.emitter(scene, hit)
        on_em = hit & (emitter != None)  # noqa: E711  (a Dr.Jit pointer comparison)
        Le = emitter.eval(si, on_em)
        L = dr.select(on_em, beta * Le, L)
        valid |= on_em
        p_em = dr.select(on_em, si.p, p_em)
        sid = dr.reinterpret_array(mi.UInt32, si.shape)
        code = dr.select(hit, code * 0x9E3779B1 + sid + 1, code)
        depth = dr.select(hit, depth + 1, depth)
        go = hit & ~on_em
        bsdf = si.bsdf(ray)
        bs, w = bsdf.sample(ctx, si, 0.5, mi.Point2f(0.5, 0.5), go)
        go &= dr.max(w) > 0.0
        beta = dr.select(go, beta * w, beta)
        ray = dr.select(go, si.spawn_ray(si.to_world(bs.wo)), ray)
        active = go
        # One kernel per bounce keeps kernels small (and re-used between bounces).
        dr.eval(L, beta, p_em, valid, code, depth, ray, active)
        if not dr.any(active):
            break
    return Chain(L, valid, p_em, code, depth)


def _integrator_class(mi):
    from mitsuba.python.ad.integrators.common import ADIntegrator

    class SpecularChainIntegrator(ADIntegrator):
        """``lfsim_specular``: :func:`specular_chain` as a Mitsuba AD integrator.

        Property ``max_depth`` (surfaces met before a path is cut, default 64).
        """

        def __init__(self, props):
            super().__init__(props)
            self.max_depth = int(props.get("max_depth", 64))

        def sample(self, mode, scene, sampler, ray, δL=None, state_in=None, active=True, **kwargs):
            c = specular_chain(scene, mi.Ray3f(ray), active, self.max_depth)
            return mi.Spectrum(c.L), c.valid, [], None

        def to_string(self):
            return f"SpecularChainIntegrator[max_depth={self.max_depth}]"

    return SpecularChainIntegrator


def register():
    """Register ``lfsim_specular`` for the current variant (idempotent)."""
    mi = mitsuba()
    key = mi.variant()
    if key not in _registered:
        cls = _integrator_class(mi)
        mi.register_integrator(NAME, lambda props: cls(props))
        _registered.add(key)
    return mi
