"""Boundary term of retinal-render derivatives, by a warped-area reparameterization of the pupil.

The analytic display path (:class:`~lfsim.render.diff_render.AnalyticRenderer`)
estimates each pixel as an integral over the eye's pupil (for a fixed film
point in the pixel)::

    I(θ) = 1/(πR²) ∫_pupil g(q, θ) dq,   g = V · E(display hit)

``g`` jumps where the ray's discrete path changes: it crosses into another
lenslet cell, is vignetted by a clear aperture (an aperture array included),
or leaves the display. The derivative of ``I`` is the interior term (AD of
``g`` along fixed samples) plus a boundary term, the jump of ``g`` times the
normal speed of those curves in the pupil, integrated along them
(Li et al. 2018). The curves are known analytically where they are drawn —
cell edges, aperture outlines, the display's rectangle — but not in the
pupil, where the integral lives.

**Method** (Bangaru, Li and Durand 2020, warped-area sampling; the same
identity as the reparameterization of Loubet et al. 2019): for any velocity
field ``𝒱(q)`` on the pupil whose normal component on every discontinuity
curve equals the curve's own normal speed, the divergence theorem on each
region where ``g`` is smooth gives, with n the rim's outward normal,

    d/dθ ∫ g dq = ∫ [∂θ g + ∇_q g · 𝒱 + g ∇_q · 𝒱] dq − ∮_rim g 𝒱 · n ds.

The last three terms are the boundary term: the area terms are estimated
with the render's own samples, the rim (a fixed boundary) with one rim point
per sample at the sample's azimuth. (Forcing 𝒱 to 0 at the rim instead, by
a rim weight, measured 10× the seed-to-seed scatter.) The field used here is built from the surfaces' own coordinates:

* for each *family* f of edges (the cells of an array surface, in units of
  the pitch; a clear aperture, in mm about its centre; optionally the
  display's rectangle, see :func:`families`), with ``c_f(q, θ)`` the ray's hit in the coordinates in which
  its edges stand still, ``𝒱_f = −(∂c_f/∂q)⁻¹ ∂θ c_f`` is the pupil motion
  that keeps the hit on f where it was: it moves every edge of f exactly
  with the sample, whatever its shape (corners included);
* ``𝒱 = Σ_f β_f 𝒱_f``, with weights ``β_f = w_f / Σ w``,
  ``w_f = 1/δ_f²``, where ``δ_f`` is the distance to f's nearest edge
  mapped to the pupil to first order. Near an edge of f its weight dominates
  (``β_f → 1``), so the normal speed is matched; ``𝒱`` is Lipschitz
  inside every smooth region of ``g``. (Where two regions meet, only the
  normal component must agree, and it does: it is the edge's speed.)

``∂c_f/∂q`` and ``∇_q g`` come from forward-mode AD in the pupil point (the
ideal eye's rays are explicit in it, :func:`~lfsim.render.diff_render.ideal_rays`);
the divergence ``∇_q · 𝒱`` from a one-sided difference of ``𝒱`` over a
step ``ε`` of the pupil point, only where the stencil point follows the same
discrete path (elsewhere that axis is left out: a share ε of the samples).
``∂θ c_f`` is not formed per parameter: the boundary term is linear in it,
so it is the reverse-mode derivative of ``B(θ) = Σ_t k_t · c_f(q_t, θ)``
with coefficients ``k_t`` fixed from the forward pass, and one backward pass
gives the total derivative for every design parameter at once
(:meth:`BoundaryTerm.objective`, used by
:meth:`~lfsim.render.diff_render.AnalyticRenderer.backward` with
``total=True``).

Texel kinks of the display's bilinear lookup are continuous in position and
need no boundary term. Only the ideal eye's rays are explicit functions of
the pupil point; the Arizona eye traces its own surfaces inside the Mitsuba
sensor, so this term is not available there (refused with a message).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .. import backend

#: One-sided step of the pupil point for the divergence of the velocity field, relative
#: to the pupil radius: far below the distance over which the field changes, far above
#: the rounding of float64 hits (measured flat from 1e-8 to 1e-4 on ini_ideal).
EPS_REL = 1e-6
#: An aperture family is left out of a pass when no traced pupil point lies within this
#: many pupil radii (first order) of its nearest edge: its outline crosses no pupil.
PRUNE_PUPILS = 3.0


@dataclass
class Family:
    """Edges that move together: ``kind`` "cells" (an array surface's lenslet cells),
    "circular" / "rectangular" (a clear aperture), or "display" (its rectangle)."""

    surface: int  # reversed-system surface index (-1: the display)
    kind: str
    name: str
    aperture: object = None


def families(renderer, with_display: bool = False) -> list[Family]:
    """Edge families of the renderer's reversed system (and the display's rectangle).

    The display is left out by default: it lies near an image of the retina (each
    lenslet images it onto the CDP), where the pupil-to-hit Jacobian is nearly
    singular and its velocity field unbounded (|J⁻¹| up to 3e7 measured on
    ini_freeform_optimized, which threw the total off by 100×). Its edge term,
    content reaching the display's border, is not included."""
    out = []
    for i, s in enumerate(renderer.map.rev.system.surfaces):
        if s.array is not None:
            out.append(Family(i, "cells", f"{s.name} cells"))
        if s.aperture is not None:
            out.append(Family(i, s.aperture.kind, f"{s.name} aperture", s.aperture))
    if with_display:
        out.append(Family(-1, "display", "display"))
    return out


def _margin(kind, c, fam, lay):
    """Distance of hits ``c`` (n, 2) to the family's nearest edge (in c's units), and that
    distance's gradient in c (n, 2): inside ≥ 0."""
    if kind == "circular":
        rr = np.hypot(c[:, 0], c[:, 1])
        g = -c / np.where(rr > 0, rr, 1.0)[:, None]
        return fam.aperture.radius - rr, g
    if kind == "cells":
        half = (0.5, 0.5)
    elif kind == "rectangular":
        half = fam.aperture.half_width
    else:  # display
        half = (0.5 * lay.width * lay.pixel_pitch, 0.5 * lay.height * lay.pixel_pitch)
    ax, ay = np.abs(c[:, 0]), np.abs(c[:, 1])
    mx, my = half[0] - ax, half[1] - ay
    use_x = mx <= my
    g = np.zeros_like(c)
    g[:, 0] = np.where(use_x, -np.sign(c[:, 0]), 0.0)
    g[:, 1] = np.where(use_x, 0.0, -np.sign(c[:, 1]))
    return np.minimum(mx, my), g


class BoundaryTerm:
    """Warped-area boundary term of an :class:`~lfsim.render.diff_render.AnalyticRenderer`.

    Parameters
    ----------
    renderer : AnalyticRenderer
        With the ideal eye.
    eps_rel : float
        Step of the pupil point for the divergence, relative to the pupil radius.
    """

    def __init__(self, renderer, eps_rel: float = EPS_REL, with_display: bool = False):
        if any(a is None for a in renderer._aims):
            raise ValueError(f"eye model {renderer.view.eye_model!r}: the boundary term of render "
                             "derivatives needs the ideal eye (its rays are explicit in the pupil point)")
        self.r = renderer
        self.families = families(renderer, with_display)
        self.R = 0.5 * float(renderer.view.pupil_diameter_mm)
        self.eps = float(eps_rel) * self.R
        self._lay = renderer.layout

    # ------------------------------------------------------------ tracing
    def _coords(self, optics, k, qx, qy, aim):
        """Trace pupil points ``(qx, qy)`` of focus ``k``; per family the hit coordinates
        ``(cx, cy)`` (Dr.Jit), plus the batch and the cell indices of every array surface."""
        from .diff_render import ideal_rays

        r = self.r
        T = r.T
        finite = r._aims[k][2]
        o, d = ideal_rays((qx, qy), aim, finite, xp=T.Array3)
        probe = []
        batch = r.trace(None, k, optics=optics, rays=(o, d, dr.full(T.Bool, True, dr.width(qx))), probe=probe)
        hits = {p.i: p for p in probe}
        coords, cells = [], []
        for f in self.families:
            if f.kind == "display":
                coords.append((batch.x, batch.y))
                continue
            h = hits[f.surface]
            if f.kind == "cells":
                coords.append((h.x / h.pitch[0], h.y / h.pitch[1]))
                cells.extend(h.cell)
            else:
                dx, dy = (float(v) for v in f.aperture.decenter)
                coords.append((h.x - dx, h.y - dy))
        return coords, batch, cells

    def _points(self, k):
        """Numpy pupil points and aims of focus ``k``: the samples, then each shifted by ε
        along x, then along y, then the point of the pupil's rim at the sample's azimuth
        (4N)."""
        q, aim, _ = self.r._aims[k]
        rr = np.hypot(q[:, 0], q[:, 1])
        u = np.where(rr[:, None] > 0, q / np.where(rr > 0, rr, 1.0)[:, None], [1.0, 0.0])
        qs = np.concatenate([q, q + [self.eps, 0.0], q + [0.0, self.eps], self.R * (1.0 - 1e-12) * u])
        return qs, np.concatenate([aim, aim, aim, aim])

    def _dr_points(self, k):
        T = self.r.T
        qs, aims = self._points(k)
        qx, qy = backend.from_numpy(T.Float, qs[:, 0].astype(T.np_dtype), qs[:, 1].astype(T.np_dtype))
        a = backend.from_numpy(T.Float, *(aims[:, j].astype(T.np_dtype) for j in range(3)))
        return qs, qx, qy, T.Array3(*a)

    def _geometry_ad(self, detached, k):
        """Hits, values and their pupil derivatives by forward-mode AD: two passes in q
        (one pass over the points twice, one tangent per copy, ran 1.5x slower)."""
        T = self.r.T
        qs, qx, qy, aim = self._dr_points(k)
        prim, tan = None, [None, None]
        for axis in (0, 1):
            qx_, qy_ = T.Float(qx), T.Float(qy)
            src = (qx_, qy_)[axis]
            dr.enable_grad(src)
            coords, batch, cells = self._coords(detached, k, qx_, qy_, aim)
            flat = [v for c in coords for v in c]
            dr.set_grad(src, 1.0)
            # forward_from, then the outputs' gradients: forward_to over several outputs
            # returned zeros for some of them (Dr.Jit 1.x, LLVM; measured on the display hit).
            dr.forward_from(src, flags=dr.ADFlag.ClearEdges)
            grads = [dr.grad(v) for v in (*flat, *batch.value)]
            dr.eval(grads, batch.valid, batch.status, cells)
            tan[axis] = [np.asarray(g, dtype=np.float64) for g in grads]
            if prim is None:
                prim = ([np.asarray(dr.detach(v), dtype=np.float64) for v in flat],
                        [np.asarray(dr.detach(v), dtype=np.float64) for v in batch.value],
                        np.asarray(batch.valid, dtype=bool),
                        [np.asarray(c) for c in cells])
            dr.disable_grad(src)
        return qs, prim, tan

    def geometry(self, leaves, k: int) -> dict:
        """What the coefficients of focus ``k`` need from the trace, independent of the
        objective: per point (the 4N of :meth:`_points`) the hit coordinates of every
        family, their Jacobians in the pupil point, the sample values and their pupil
        gradients, validity and cells; the pupil derivatives by forward-mode AD
        (one-sided differences of a primal trace at ε instead disagreed with AD by up to
        6x on ini_freeform_optimized, and were not faster)."""
        detached = [dr.detach(v) for v in leaves]
        nf = len(self.families)
        qs, prim, tan = self._geometry_ad(detached, k)
        flat, values, valid, cells = prim
        n = qs.shape[0] // 4
        # Same discrete path as the sample: valid, and the same cell on every array surface.
        same = valid & np.tile(valid[:n], 4)
        for cc in cells:
            same &= np.tile(cc[:n], 4) == cc
        # Per family: −J⁻¹ (the field per unit ∂θc) and the weight 1/δ² of the pupil-space
        # distance δ to the family's nearest edge.
        Ms, ws, active = [], [], []
        for j, f in enumerate(self.families):
            c = np.stack([flat[2 * j], flat[2 * j + 1]], axis=1)
            J = np.empty((qs.shape[0], 2, 2))
            for a in (0, 1):
                J[:, 0, a] = tan[a][2 * j]
                J[:, 1, a] = tan[a][2 * j + 1]
            m, gm = _margin(f.kind, c, f, self._lay)
            slope = np.hypot(*np.einsum("nab,na->nb", J, gm).T)
            dist = np.maximum(m, 0.0) / np.where(slope > 0, slope, np.inf)
            if f.kind != "cells" and not np.any(valid & (dist < PRUNE_PUPILS * self.R)):
                # No edge of this aperture comes near any traced pupil: no discontinuity
                # to follow (the field stays valid without it; only its variance changes).
                continue
            det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
            ok = valid & np.isfinite(det) & (np.abs(det) > 1e-300) & np.all(np.isfinite(J), axis=(1, 2))
            inv = np.zeros_like(J)
            dd = np.where(ok, det, 1.0)
            inv[:, 0, 0], inv[:, 1, 1] = J[:, 1, 1] / dd, J[:, 0, 0] / dd
            inv[:, 0, 1], inv[:, 1, 0] = -J[:, 0, 1] / dd, -J[:, 1, 0] / dd
            Ms.append(np.where(ok[:, None, None], -inv, 0.0))
            ws.append(np.where(ok, 1.0 / np.maximum(dist, 1e-12 * self.R) ** 2, 0.0))
            active.append(j)
        wsum = np.sum(ws, axis=0)
        beta = [np.where(wsum > 0, w / np.where(wsum > 0, wsum, 1.0), 0.0) for w in ws]
        g = np.stack(values, axis=1)  # (4N, C)
        grad_g = np.nan_to_num(np.stack([np.stack(tan[a][2 * nf:], axis=1) for a in (0, 1)], axis=-1))
        return {"k": k, "qs": qs, "n": n, "g": g, "grad_g": grad_g, "valid": valid, "same": same,
                "active": active, "BM": [b[:, None, None] * M for b, M in zip(beta, Ms)]}

    def coefficients(self, leaves, k: int, weights: np.ndarray, geom: dict | None = None):
        """Fixed coefficients of :meth:`objective` for focus ``k``.

        ``weights``: (N, C) derivative of the objective with respect to each sample's
        value (``a_s``); ``geom``: :meth:`geometry` of these leaves (computed if not
        given). Returns ``(mask, [(kx, ky)] per family)`` as numpy arrays over the 4N
        points (None for a family left out, see :data:`PRUNE_PUPILS`), and the number of
        points that carry a term.
        """
        G_ = self.geometry(leaves, k) if geom is None else geom
        n, qs, g, valid, same = G_["n"], G_["qs"], G_["g"], G_["valid"], G_["same"]
        n4 = qs.shape[0]
        # Sample-side factors: A = Σ_c a g (for the divergence), G = Σ_c a ∇g (for ∇g·𝒱).
        a = np.zeros((n4, g.shape[1]))
        a[:n] = weights
        A = np.where(valid[:n], np.sum(a[:n] * g[:n], axis=1), 0.0)
        G = np.where(valid[:n, None], np.einsum("nc,nca->na", a[:n], G_["grad_g"][:n]), 0.0)
        ok_e = [same[n:2 * n], same[2 * n:3 * n]]  # stencil point along x / y usable
        rim = slice(3 * n, 4 * n)
        A_rim = np.sum(weights * g[rim], axis=1) * valid[rim]
        nrm = qs[rim] / self.R
        out = []
        e_vec = np.eye(2)
        for BM in G_["BM"]:  # β_f M_f  (4N, 2, 2)
            kvec = np.zeros((n4, 2))
            # centre: β M^T G − A Σ_e ok_e/ε β M^T e
            kvec[:n] = np.einsum("nab,na->nb", BM[:n], G)
            for ax in (0, 1):
                s = A * ok_e[ax] / self.eps
                kvec[:n] -= s[:, None] * np.einsum("nab,a->nb", BM[:n], e_vec[ax])
                sl = slice((ax + 1) * n, (ax + 2) * n)
                kvec[sl] += s[:, None] * np.einsum("nab,a->nb", BM[sl], e_vec[ax])
            # Flux through the rim: −∮ g 𝒱·n ds / (πR²) = −(2/R) E_φ[g 𝒱·n].
            kvec[rim] = -(2.0 / self.R) * A_rim[:, None] * np.einsum("nab,na->nb", BM[rim], nrm)
            out.append(np.where(np.isfinite(kvec), kvec, 0.0))
        mask = np.zeros(n4, dtype=bool)
        mask[:n] = valid[:n]
        mask[n:3 * n] = np.concatenate(ok_e)
        mask[3 * n:] = valid[3 * n:]
        # Families left out by the geometry (no edge near any pupil) carry no coefficients.
        full = [None] * len(self.families)
        for j, kk in zip(G_["active"], out):
            full[j] = kk
        return mask, full, int(np.count_nonzero(mask))

    def jacobian(self, values, wrt, k: int) -> np.ndarray:
        """Boundary term of the per-pixel derivatives of focus ``k``'s image:
        ``(H·W, C, len(wrt))``, the part of ``dI_p/dP_i`` that the interior (AD along
        fixed samples) leaves out, for the design-vector entries ``wrt`` at ``values``.

        The coefficients are those of :meth:`coefficients` with a sample's weight
        ``1/spp`` on its own pixel and channel (linear in the weights, so one
        :meth:`geometry` serves every channel); ``∂θ c_f`` comes from one forward-mode
        pass per parameter over the 4N points, and each point's term goes to its
        sample's pixel."""
        r = self.r
        T = r.T
        P0 = r.params(values)
        with dr.suspend_grad():
            leaves = [dr.detach(v) for v in r.optics(P0)]
        geom = self.geometry(leaves, k)
        n = geom["n"]
        C = geom["g"].shape[1]
        pix = (np.arange(4 * n) % n) // r.spp
        coef = []
        for c in range(C):
            w = np.zeros((n, C))
            w[:, c] = 1.0 / r.spp
            mask, kv, _ = self.coefficients(leaves, k, w, geom)
            coef.append([(j, np.where(mask[:, None], kk, 0.0)) for j, kk in enumerate(kv) if kk is not None])
        qs, qx, qy, aim = self._dr_points(k)
        base = np.asarray(values if values is not None else r.values0, dtype=np.float64)
        out = np.zeros((r.n_pixels, C, len(wrt)))
        for col, i in enumerate(wrt):
            t = dr.zeros(T.Float, 1)
            dr.enable_grad(t)
            e = np.zeros(len(r.names))
            e[int(i)] = 1.0
            coords, _, _ = self._coords(r.optics(r.params(base) + t * T.Float(e)), k, qx, qy, aim)
            flat = [v for cc in coords for v in cc]
            dr.forward_from(t)
            grads = [dr.grad(v) for v in flat]
            dr.eval(grads)
            dc = [np.nan_to_num(np.asarray(gv, dtype=np.float64)) for gv in grads]
            for c in range(C):
                term = sum(kk[:, 0] * dc[2 * j] + kk[:, 1] * dc[2 * j + 1] for j, kk in coef[c])
                out[:, c, col] = np.bincount(pix, weights=term, minlength=r.n_pixels)
        return out

    def objective(self, leaves, k: int, weights: np.ndarray):
        """``B(leaves) = Σ_t Σ_f k_t · c_f(q_t)``: its reverse-mode derivative is the boundary
        term of focus ``k`` for the objective whose per-sample weights are ``weights``."""
        r = self.r
        T = r.T
        mask, kv, _ = self.coefficients(leaves, k, weights)
        qs, qx, qy, aim = self._dr_points(k)
        coords, _, _ = self._coords(leaves, k, qx, qy, aim)
        m = backend.from_numpy(T.Float, mask.astype(np.float64)) > 0.5
        total = T.Float(0.0)
        zero = np.zeros((mask.size, 2))
        for (cx, cy), kk in zip(coords, kv):
            # A family left out keeps zero coefficients (not a skipped term): the kernel
            # then does not depend on which families a pass left out.
            kk = zero if kk is None else kk
            kx, ky = backend.from_numpy(T.Float, kk[:, 0].astype(T.np_dtype), kk[:, 1].astype(T.np_dtype))
            term = dr.select(m, kx * cx + ky * cy, 0.0)
            total = total + dr.sum(term)
        return total

