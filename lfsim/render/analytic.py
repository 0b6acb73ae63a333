"""The analytic display path: eye rays traced back through the exact design.

A ray that leaves the eye's pupil on the viewing window toward the eyepiece is
traced backwards through the design's own surfaces (the sequential tracer of
the metrics, :func:`lfsim.optics.reverse.reversed_system`) to the display
plane, where it reads the display's radiance. No optics meshes are involved:
this is the reference the mesh path is measured against. Rays that the real
optics vignette (clear apertures, an aperture array, a failed TIR) carry
weight 0; by default a ray that crosses between lenslet cells inside the MLA
goes on through the neighbouring lenslet (crosstalk, see ``cells``).
Spectral renders (:mod:`.spectra`) give the tracer one parameter block per
wavelength node, the glass indices at that wavelength, and each ray is traced
with its node's block; a monochrome render has one block (by default the
design's primary wavelength).
"""

from __future__ import annotations

import drjit as dr
import numpy as np

from .. import backend
from ..optics.reverse import reversed_system
from ..optics.tracer import RayState, SequentialTracer


class ReverseOptics:
    """The design of one CDP state, traced from the viewing window to the display.

    Parameters
    ----------
    model : lfsim.ini.model.IniModel
    k : int
        CDP state (the tunable lens's power).
    precision : str
        ``"float32"`` (default: Mitsuba's RGB variants) or ``"float64"``.
    cells : {"per_surface", "fixed"}
        Lenslet arrays: ``"per_surface"`` (default) treats the MLA as one
        piece of glass, so a ray that crosses into a neighbouring cell inside
        it leaves through that lenslet's face (crosstalk is rendered, as the
        mesh path does); ``"fixed"`` keeps each ray in the cell it entered,
        as if the cells were baffled (an ideal aperture array).
    """

    def __init__(self, model, k: int = 0, precision: str = "float32", cells: str = "per_surface",
                 wavelengths=None, diffraction_pupil_mm: float | None = None):
        self.model = model
        self.cells = cells
        spec, system = model.spec, model.system
        values = model.values(k)
        frames = model.tracer.frames_numpy(model.tracer.params(values=values))
        powers = {}
        if spec.tunable is not None:
            name = system.surfaces[spec.tunable].name
            powers[name] = float(values[model.tracer.index[f"{name}.power"]])
        self.system = reversed_system(system, frames, end_plane_z=-model.g, first=0,
                                      last=spec.viewing_window - 1, powers=powers)
        self.tracer = SequentialTracer(self.system, precision)
        self.T = self.tracer.T
        from .spectra import monochrome

        #: Wavelength nodes of the pass (:class:`lfsim.render.spectra.Wavelengths`): one parameter block each.
        self.wavelengths = wavelengths if wavelengths is not None else monochrome(model.lam)[0]
        self.wavelength_nm = self.wavelengths.nm[0] if self.wavelengths.count == 1 else model.lam
        #: Diffraction of each elemental view's aperture for an eye pupil of this diameter
        #: (:class:`lfsim.render.diffraction.ViewApertureKick`), applied at the lenslet stop.
        self.diffraction = None
        if diffraction_pupil_mm is not None:
            from .diffraction import ViewApertureKick

            self.diffraction = ViewApertureKick(model, k, diffraction_pupil_mm, self.T)
            stop = system.surfaces[spec.stop].name
            self._stop = next(j for j, s in enumerate(self.system.surfaces) if s.name == stop)
            self._nodes_nm = self.T.Float(np.asarray(self.wavelengths.nm, dtype=self.T.np_dtype))
            dr.make_opaque(self._nodes_nm)
        self.R_vw = np.asarray(model.R_vw, dtype=np.float64)
        self.o_vw = np.asarray(model.o_vw, dtype=np.float64)
        self._P = None

    def params(self):
        if self._P is None:
            self._P = self.tracer.params(list(self.wavelengths.nm))
        return self._P

    def to_global(self, o_local, d_local):
        """Viewing-window-frame Dr.Jit points/vectors to the global frame."""
        T, c = self.T, self.tracer.const  # the frame as opaque data (one kernel for any design)
        R = T.Matrix3(*(c(v) for v in self.R_vw.ravel()))
        return T.Array3(R @ T.Array3(o_local)) + T.Array3(*(c(v) for v in self.o_vw)), R @ T.Array3(d_local)

    def to_display(self, o_local, d_local, block=None, kick_u=None):
        """Trace eye rays (viewing-window frame, heading −z) back to the display.

        ``block``: each ray's wavelength node (UInt32; default node 0).
        ``kick_u``: two uniform numbers per ray, for the diffraction of the view's aperture
        (optics built with ``diffraction_pupil_mm``).
        Returns ``(p, d, valid)``: the hit on the display plane and the
        direction there (global frame, Dr.Jit) and whether the ray got
        through every surface.
        """
        kick = None
        if self.diffraction is not None and kick_u is not None:
            T = self.T
            # Where the ray crosses the viewing-window plane: the pupil point of its view.
            ol, dl_ = T.Array3(o_local), T.Array3(d_local)
            t = -ol.z / dr.select(dr.abs(dl_.z) > 0.0, dl_.z, 1.0)
            q = (dr.fma(dl_.x, t, ol.x), dr.fma(dl_.y, t, ol.y))
            nodes = dr.zeros(T.UInt32, dr.width(ol.x)) if block is None else T.UInt32(block)
            lam_mm = dr.gather(T.Float, self._nodes_nm, nodes) * 1e-6
            kd, u1, u2 = self.diffraction, kick_u[0], kick_u[1]

            def f(dd, hit, cell, n_on):
                return kd.kick(dd, hit, cell, q, lam_mm / n_on, u1, u2)

            kick = (self._stop, f)
        o, d = self.to_global(o_local, d_local)
        if block is not None:
            block = self.T.UInt32(block)
        out = self.tracer.trace(self.params(), RayState(o, d), block=block, cells=self.cells, kick=kick)
        return out.p, out.d, out.status == 0

    def to_display_numpy(self, o_local: np.ndarray, d_local: np.ndarray, block=None):
        """:meth:`to_display` for numpy (N, 3) arrays (``block``: numpy node indices); numpy results."""
        T = self.T
        o = backend.from_numpy(T.Float, *np.asarray(o_local, dtype=T.np_dtype).T)
        d = backend.from_numpy(T.Float, *np.asarray(d_local, dtype=T.np_dtype).T)
        if block is not None:
            block = T.UInt32(np.broadcast_to(np.asarray(block, dtype=np.uint32), (len(o_local),)).copy())
        with dr.suspend_grad():
            p, dd, ok = self.to_display(T.Array3(*o), T.Array3(*d), block)
            dr.eval(p, dd, ok)
        return (np.stack([np.asarray(p[i], dtype=np.float64) for i in range(3)], axis=1),
                np.stack([np.asarray(dd[i], dtype=np.float64) for i in range(3)], axis=1),
                np.asarray(ok, dtype=bool))
