"""First-order references of many linear views of one InI design at once.

:meth:`lfsim.ini.model.IniModel.linear_views` re-linearizes a design at other
parameter values (for central differences of first-order quantities). Each
view answers :meth:`~IniModel.paraxial_vw`, :meth:`~IniModel.ei_centers` and
:meth:`~IniModel.state` one view and one call at a time. :class:`StackedViews`
holds the views' paraxial maps stacked along a leading axis V and evaluates
the same formulas (Eqs. 1, 2 and 5 generalized, as in the model) for every
view in a few array operations:

* the EI layout (display points of the sampled fields, Eq. 1–2),
* the paraxial chief rays' retinal tangents (the GD reference, Eq. 11),
* the paraxial marginal rays' viewing-window positions and the footprint
  width d_v (the PA reference, Eq. 12, and Eq. 5),
* the relay–eyepiece focal length per CDP state.

The arithmetic is the model's, so a stack of one view gives the model's own
numbers (tested to 1e-13 against the per-view methods).
"""

from __future__ import annotations

import numpy as np

from ..metrics import pupil


def _mv(A, v):
    """Matrix (…, i, j) times vector (…, j), broadcasting the leading axes."""
    return (A @ v[..., None])[..., 0]


class StackedViews:
    """Paraxial maps of V views of one model, stacked (see the module docstring).

    Parameters
    ----------
    model : IniModel
        Supplies the lattice, the stop half-widths and the reference lenslet.
    views : list of IniModel
        Views of ``model`` (from ``model.linear_views``), or ``[model]``.
    """

    def __init__(self, model, views):
        self.model = model
        self.V = len(views)
        self.S0 = np.stack([v.S0 for v in views])  # (V, 2)
        self.JS = np.stack([v.JS for v in views])  # (V, 2, 4)
        self.L0 = np.stack([v.L0 for v in views])  # (V, 4)
        self.JL = np.stack([v.JL for v in views])  # (V, 4, 4)
        self.G0 = np.stack([np.asarray(v.G0) for v in views])  # (V, nd, 4)
        self.JG = np.stack([np.asarray(v.JG) for v in views])  # (V, nd, 4, 4)
        self.inv_t = np.linalg.inv(self.JS[:, :, 2:])  # (V, 2, 2): stop hit per launch slope
        self.stop_half = np.asarray(model.stop_half, dtype=np.float64)
        self.c_ref = np.asarray(model.c_ref, dtype=np.float64)

    def _lift(self, a, batch: int):
        """(V, …) map → (V, 1 × batch, …) to broadcast against inputs with ``batch`` axes."""
        return a.reshape(a.shape[:1] + (1,) * batch + a.shape[1:])

    def paraxial_vw(self, k: int, s, c, rho, per_view: bool = False):
        """Paraxial viewing-window states (V, *B, 4) of rays (s, c, rho) in state k
        (:meth:`IniModel.aim` then :meth:`IniModel.affine`, per view). The inputs are
        (*B, 2), the same rays in every view, or with ``per_view`` (V, *B, 2), view v's
        rays in view v."""
        s, c, rho = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (s, c, rho)))
        B = s.ndim - (2 if per_view else 1)
        target = rho * self.stop_half - self._lift(self.S0, B) - _mv(self._lift(self.JS[:, :, :2], B), s - c)
        t = _mv(self._lift(self.inv_t, B), target)
        JG = self.JG[:, k]
        A = JG @ self.JL
        shift = np.zeros(c.shape[:-1] + (4,))
        shift[..., :2] = c - self.c_ref
        b = _mv(self._lift(JG, B), self._lift(self.L0, B) + shift) + self._lift(self.G0[:, k], B)
        u = np.concatenate([np.broadcast_to(s - c, t.shape), t], axis=-1)
        return b + _mv(self._lift(A, B), u)

    def ei_centers(self, k: int, m, n) -> np.ndarray:
        """Display positions (V, *B, 2) of the EI centres of lenslets (m, n) in state k:
        the paraxial chief ray through the lenslet's stop centre crosses the VW centre."""
        c = self.model.lenslet_center(m, n)
        zero = np.zeros_like(c)
        p0 = self.paraxial_vw(k, c, c, zero)[..., :2]
        cols = [self.paraxial_vw(k, c + e, c, zero)[..., :2] - p0 for e in np.eye(2)]
        As = np.stack(cols, axis=-1)
        return c - np.linalg.solve(As, p0[..., None])[..., 0]

    def ei_pitch(self, k: int) -> np.ndarray:
        """EI pitch on the display (V, 2) (Eq. 2 generalized)."""
        mo = self.model
        a = self.ei_centers(k, np.array([mo.m_ref, mo.m_ref + 1, mo.m_ref]),
                            np.array([mo.n_ref, mo.n_ref, mo.n_ref + 1]))
        return np.stack([a[:, 1, 0] - a[:, 0, 0], a[:, 2, 1] - a[:, 0, 1]], axis=-1)

    def d_v(self, k: int) -> np.ndarray:
        """Footprint width on the viewing window (V, 2) of the reference lenslet (Eq. 5)."""
        mo = self.model
        s0 = self.ei_centers(k, mo.m_ref, mo.n_ref)  # (V, 2)
        out = []
        for ax in range(2):
            e = np.eye(2)[ax]
            c = np.broadcast_to(self.c_ref, s0.shape)
            plus = self.paraxial_vw(k, s0, c, np.broadcast_to(e, s0.shape), per_view=True)  # (V, 4)
            minus = self.paraxial_vw(k, s0, c, np.broadcast_to(-e, s0.shape), per_view=True)
            out.append(np.abs(plus[:, ax] - minus[:, ax]))
        return np.stack(out, axis=-1)

    def _theta_ei(self, k: int):
        """Per axis, the tangent-space angle (V,) one elemental image subtends from the
        viewing window (Eq. 8's θ), with the EI centre (V, 2), the EI pitch (V, 2) and
        the retinal tangent map of state k."""
        mo = self.model
        c = self.c_ref
        s0 = self.ei_centers(k, mo.m_ref, mo.n_ref)  # (V, 2)
        pei = self.ei_pitch(k)  # (V, 2)
        cb = np.broadcast_to(c, s0.shape)
        z = np.zeros_like(s0)
        D = mo.depths[k] / 1000.0

        def retinal(st):
            return st[..., 2:4] - st[..., 0:2] * D

        theta = []
        for ax in range(2):
            e = np.eye(2)[ax]
            hp = 0.5 * pei[:, ax:ax + 1] * e  # (V, 2)
            ep = self.paraxial_vw(k, s0 + hp, cb, z, per_view=True)
            em = self.paraxial_vw(k, s0 - hp, cb, z, per_view=True)
            theta.append(np.abs(retinal(ep)[:, ax] - retinal(em)[:, ax]))
        return theta, s0, pei, cb, z, retinal

    def fov_deg(self, k: int) -> np.ndarray:
        """Full FOV (V, 2) in degrees between the edge EI centres' outer edges, x and y
        (:meth:`IniModel.state`'s ``fov_deg``: Eqs. 7–9 generalized)."""
        mo = self.model
        M, N = mo.arr.m, mo.arr.n
        theta, s0, _, cb, z, retinal = self._theta_ei(k)
        r0 = retinal(self.paraxial_vw(k, s0, cb, z, per_view=True))
        s1 = self.ei_centers(k, mo.m_ref + 1, mo.n_ref + 1)
        c1 = np.broadcast_to(mo.lenslet_center(mo.m_ref + 1, mo.n_ref + 1), s1.shape)
        r1 = retinal(self.paraxial_vw(k, s1, c1, z, per_view=True))
        delta = np.abs(r1 - r0)
        return np.stack([2.0 * np.degrees(np.arctan(0.5 * (nl - 1) * delta[:, i] + 0.5 * theta[i]))
                         for i, nl in enumerate((M, N))], axis=-1)

    def pixel_arcmin(self, k: int) -> np.ndarray:
        """One display pixel (V, 2) seen from the viewing window, arcmin, x and y
        (:meth:`IniModel.state`'s ``pixel_arcmin``: the EI's angle over its pitch, times
        the pixel pitch)."""
        theta, _, pei, _, _, _ = self._theta_ei(k)
        pitch = self.model.spec.pixel_pitch
        return np.stack([60.0 * np.degrees(np.arctan(theta[ax] / pei[:, ax] * pitch)) for ax in range(2)], axis=-1)

    def display_points(self, m, n, k, fields) -> np.ndarray:
        """Display points (V, S, F, 2) of field fractions (F, 2) in the EIs of lenslets
        (m, n) at states k (:func:`lfsim.ini.subsystems.display_points`, per view)."""
        m, n, k = (np.asarray(a).reshape(-1) for a in (m, n, k))
        fields = np.asarray(fields, dtype=np.float64)
        ppe = np.array(self.model.spec.pixels_per_ei, dtype=np.float64)
        out = np.empty((self.V, len(m), fields.shape[-2], 2))
        for kk in sorted(set(k.tolist())):
            sel = k == kk
            s0 = self.ei_centers(kk, m[sel], n[sel])  # (V, S_k, 2)
            half = 0.5 * self.ei_pitch(kk) * (1.0 - 1.0 / ppe)  # (V, 2)
            out[:, sel] = s0[:, :, None, :] + fields[None, None] * half[:, None, None, :]
        return out

    def references(self, subs, display=None) -> dict:
        """The first-order references of sub-systems ``subs`` in every view: ``display``
        (V, S, F, 2), ``par_c`` (V, S, F, 2) paraxial retinal tangents of the chief rays,
        ``par_m`` (V, S, F, 4, 2) paraxial VW positions of the four marginal rays, ``d_v``
        (V, S), ``efl`` (V, n_states), ``fov`` (V, n_states, 2) in degrees, ``pixel`` (V, n_states, 2)
        in arcmin, ``ei_pitch`` (V, n_states, 2) in mm. ``display``:
        the rays' display points when they are given (the traced ones), else the views'
        own layout."""
        mo = self.model
        if display is None:
            display = self.display_points(subs.m, subs.n, subs.k, subs.fields)
        V, S, F = display.shape[:3]
        par_c = np.empty((V, S, F, 2))
        par_m = np.empty((V, S, F, 4, 2))
        d_v = np.empty((V, S))
        for kk in np.unique(subs.k):
            kk = int(kk)
            sel = subs.k == kk
            sd = display[:, sel]  # (V, S_k, F, 2)
            c = np.broadcast_to(subs.center[sel][None, :, None, :], sd.shape)
            pc = self.paraxial_vw(kk, sd, c, np.zeros_like(sd), per_view=True)
            par_c[:, sel] = pc[..., 2:4] - pc[..., 0:2] * (mo.depths[kk] / 1000.0)
            sm = np.broadcast_to(sd[:, :, :, None, :], sd.shape[:3] + (4, 2))
            cm = np.broadcast_to(c[:, :, :, None, :], sm.shape)
            rho = np.broadcast_to(pupil.MARGINAL, sm.shape)
            par_m[:, sel] = self.paraxial_vw(kk, sm, cm, rho, per_view=True)[..., 0:2]
            d_v[:, sel] = np.mean(self.d_v(kk), axis=-1)[:, None]
        with np.errstate(divide="ignore"):
            efl = -0.5 * (1.0 / self.JG[:, :, 2, 0] + 1.0 / self.JG[:, :, 3, 1])
        fov = np.stack([self.fov_deg(k) for k in range(len(mo.depths))], axis=1)
        pixel = np.stack([self.pixel_arcmin(k) for k in range(len(mo.depths))], axis=1)
        ei_pitch = np.stack([self.ei_pitch(k) for k in range(len(mo.depths))], axis=1)
        return dict(display=display, par_c=par_c, par_m=par_m, d_v=d_v, efl=efl, fov=fov, pixel=pixel,
                    ei_pitch=ei_pitch)
