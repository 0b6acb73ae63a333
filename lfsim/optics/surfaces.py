"""Surface geometry in Dr.Jit: sag, gradient, normal and ray intersection.

All functions work in a surface's local frame (vertex at the origin, axis +z)
on Dr.Jit arrays of any width and precision; they are generic over the array
types passed in. The surface model is documented in
:mod:`lfsim.optics.prescription`.

Intersections return ``(t, ok)``: the ray parameter of the hit on the branch
of the surface that passes through the vertex, and a mask of rays that have
such a hit. Nothing here produces NaN: square-root and division arguments are
guarded with ``dr.select`` and failing lanes are parked on finite values.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr


@dataclass
class Shape:
    """Per-ray (or broadcast) shape coefficients of one surface.

    ``asphere`` maps even orders (4..16) to coefficient arrays and ``xy``
    maps (i, j) to c_ij arrays; ``inv_norm`` is 1/R_n.
    """

    c: object
    k: object
    asphere: dict
    xy: dict
    inv_norm: object

    def detached(self) -> Shape:
        return Shape(
            dr.detach(self.c),
            dr.detach(self.k),
            {o: dr.detach(v) for o, v in self.asphere.items()},
            {ij: dr.detach(v) for ij, v in self.xy.items()},
            dr.detach(self.inv_norm),
        )


def sag(x, y, s: Shape):
    """Sag z(x, y) and its partial derivatives (z, ∂z/∂x, ∂z/∂y) and a domain mask.

    The mask is false where the base conic is undefined
    (1 − (1+k) c² r² ≤ 0).
    """
    r2 = dr.fma(x, x, y * y)
    arg = 1.0 - (1.0 + s.k) * s.c * s.c * r2
    # arg = 0 is the rim of a hemisphere, where the slope is infinite: outside.
    inside = arg > 0.0
    root = dr.sqrt(dr.select(inside, arg, 1.0))
    z = s.c * r2 / (1.0 + root)
    # d z / d(r²) · 2 = c / root  →  ∂z/∂x = x c / root
    g = s.c / root
    if s.asphere:
        # q(r²) = Σ A_{2i} r^{2(i−2)}, dq = Σ i A_{2i} r^{2(i−2)} by Horner, so
        # Σ A_{2i} r^{2i} = q r⁴ and its derivative w.r.t. r² is dq r².
        top = max(s.asphere) // 2
        q = 0.0
        dq = 0.0
        for i in range(top, 1, -1):
            a = s.asphere.get(2 * i)
            q = q * r2 if a is None else q * r2 + a
            dq = dq * r2 if a is None else dq * r2 + i * a
        z = z + q * r2 * r2
        g = g + 2.0 * dq * r2
    zx = x * g
    zy = y * g
    if s.xy:
        u = x * s.inv_norm
        v = y * s.inv_norm
        imax = max(i for i, _ in s.xy)
        jmax = max(j for _, j in s.xy)
        up = [1.0, u]
        for _ in range(2, imax + 1):
            up.append(up[-1] * u)
        vp = [1.0, v]
        for _ in range(2, jmax + 1):
            vp.append(vp[-1] * v)
        fz = 0.0
        fx = 0.0
        fy = 0.0
        for (i, j), cij in s.xy.items():
            fz = fz + cij * (up[i] * vp[j])
            if i > 0:
                fx = fx + (cij * i) * (up[i - 1] * vp[j])
            if j > 0:
                fy = fy + (cij * j) * (up[i] * vp[j - 1])
        z = z + fz
        zx = zx + fx * s.inv_norm
        zy = zy + fy * s.inv_norm
    return z, zx, zy, inside


def normal(zx, zy, Array3):
    """Unit surface normal (−∂z/∂x, −∂z/∂y, 1)/|…| (points toward +z local)."""
    return dr.normalize(Array3(-zx, -zy, 1.0))


def intersect_conic(p, d, c, k):
    """Exact intersection with the base conic c(x² + y² + (1+k) z²) − 2z = 0.

    The ray is first moved to the vertex plane (z = 0) so the quadratic is
    solved near the vertex, then the root on the vertex branch is taken with
    the cancellation-free form ``t = −C / (B + sign(B)·√(B² − AC))``, which
    tends to the plane solution as c → 0 for either propagation direction.
    """
    # Rays (nearly) parallel to the vertex plane are solved from where they are.
    dz_ok = dr.abs(d.z) > 1e-9
    t0 = dr.select(dz_ok, -p.z / dr.select(dz_ok, d.z, 1.0), 0.0)
    x = dr.fma(d.x, t0, p.x)
    y = dr.fma(d.y, t0, p.y)
    z = dr.select(dz_ok, 0.0, p.z)
    ek = 1.0 + k
    A = c * (dr.fma(d.x, d.x, d.y * d.y) + ek * d.z * d.z)
    B = c * (x * d.x + y * d.y + ek * z * d.z) - d.z
    C = c * (dr.fma(x, x, y * y) + ek * z * z) - 2.0 * z
    disc = B * B - A * C
    ok = disc >= 0.0
    root = dr.sqrt(dr.select(ok, disc, 0.0))
    den = B + dr.copysign(root, B)
    ok &= den != 0.0
    t1 = dr.select(ok, -C / dr.select(ok, den, 1.0), 0.0)
    return t0 + t1, ok


def intersect(p, d, s: Shape, T, newton: bool, tol: float, max_iter: int):
    """Ray/surface intersection (t, ok, converged).

    Conics are solved in closed form. Aspheres and XY polynomials start from
    the base-conic root (or the vertex plane if the conic is missed) and are
    refined by Newton's method on f(t) = z(t) − sag(x(t), y(t)) in a detached
    symbolic loop (tolerance ``tol`` on |Δt|, at most ``max_iter`` steps); one
    final Newton step is taken with gradients attached, which gives the exact
    implicit derivative dt/dθ = −(∂f/∂θ)/(∂f/∂t) at the converged root.
    """
    t, ok = intersect_conic(p, d, s.c, s.k)
    if not newton:
        return t, ok, T.Bool(True)

    with dr.suspend_grad():
        pd_, dd_ = dr.detach(p), dr.detach(d)
        sd = s.detached()
        dz_ok = dr.abs(dd_.z) > 1e-9
        t_plane = dr.select(dz_ok, -pd_.z / dr.select(dz_ok, dd_.z, 1.0), 0.0)
        t_start = dr.select(ok, dr.detach(t), t_plane)

        def cond(t, it, done):
            return (it < max_iter) & ~done

        def body(t, it, done):
            step, good = _newton_step(pd_, dd_, t, sd)
            return t - step, it + 1, (dr.abs(step) <= tol) | ~good

        t_conv, _, _ = dr.while_loop(
            state=(T.Float(t_start), dr.zeros(T.UInt32, dr.width(t_start)), T.Bool(False)),
            cond=cond,
            body=body,
            labels=("t", "it", "done"),
            label="lfsim_newton",
        )

    # One attached Newton step: exact value, implicit gradient.
    step, good = _newton_step(p, d, t_conv, s)
    converged = good & (dr.abs(dr.detach(step)) <= 10.0 * tol)
    return t_conv - step, good, converged


def _newton_step(p, d, t, s: Shape):
    """Newton step f/f' for f(t) = z(t) − sag(x(t), y(t)), and a validity mask."""
    q = dr.fma(d, t, p)
    z, zx, zy, inside = sag(q.x, q.y, s)
    f = q.z - z
    fp = d.z - zx * d.x - zy * d.y
    good = inside & (dr.abs(fp) > 1e-12)
    return dr.select(good, f / dr.select(good, fp, 1.0), 0.0), good
