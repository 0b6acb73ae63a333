"""Prism thickness (lfsim.optics.solids) against independent line–surface roots."""

import numpy as np
import pytest
from scipy.optimize import brentq

import lfsim
from lfsim.optics import solids


@pytest.fixture(scope="module")
def freeform():
    from pathlib import Path

    d = lfsim.load(Path(__file__).resolve().parents[1] / "scenes" / "ini_freeform.toml")
    tr = d.tracer("float64")
    v = np.asarray(d.system.parameter_values(d.system.primary_wavelength_nm))
    return d, tr, v


def _root_distance(tr, frames, b, P, u):
    """Distance along P + t·u to surface b: a bracketed root of z_local − sag, scanning t in
    (0, 80] mm, with the aperture check; None when the line misses b's aperture."""
    R, o = frames[b]
    ap = tr.system.surfaces[b].aperture

    def f(t):
        q = (P + t * u - o) @ R
        return q[2] - float(tr.sag_numpy(b, np.array([q[0]]), np.array([q[1]]))[0])

    ts = np.linspace(1e-6, 80.0, 801)
    fs = np.array([f(t) for t in ts])
    for k in np.flatnonzero(np.isfinite(fs[:-1]) & np.isfinite(fs[1:]) & (np.sign(fs[:-1]) != np.sign(fs[1:]))):
        t = brentq(f, ts[k], ts[k + 1], xtol=1e-13)
        q = (P + t * u - o) @ R
        dx, dy = q[0] - ap.decenter[0], q[1] - ap.decenter[1]
        inside = (np.hypot(dx, dy) <= ap.radius if ap.kind == "circular"
                  else abs(dx) <= ap.half_width[0] and abs(dy) <= ap.half_width[1])
        return t if inside else None
    return None


def test_prism_faces_and_opposite_pairs(freeform):
    d, tr, v = freeform
    names = [s.name for s in d.system.surfaces]
    assert [[names[i] for i in run] for run in solids.prisms(d.system)] == [["S1", "S2", "S3", "S4"]]
    th, sampled = solids.prism_thickness(tr, v, points=9)
    assert [names[i] for i, _ in sampled] == ["S1", "S2", "S3", "S4"]
    per = np.split(th[0], np.cumsum([len(xy) for _, xy in sampled])[:-1])
    # S1 meets S2 and S3 at edges (no opposite face): no thickness; the front and back are measured.
    assert np.all(np.isinf(per[0]))
    for k in (1, 2, 3):
        fin = per[k][np.isfinite(per[k])]
        assert fin.size > 10 and np.all(fin > 15.0) and np.all(fin < 40.0)
    assert not np.isnan(th).any()


def test_prism_thickness_matches_bracketed_roots(freeform):
    """Every finite thickness of S3 (the mirror) equals the first root of the tracer's sag
    along the face normal into the glass, found by bisection-safe root finding."""
    d, tr, v = freeform
    th, sampled = solids.prism_thickness(tr, v, points=7)
    frames = tr.frames_numpy()
    names = [s.name for s in d.system.surfaces]
    i3 = names.index("S3")
    q0 = 0
    for i, xy in sampled:
        if i == i3:
            break
        q0 += len(xy)
    xy = dict(sampled)[i3]
    R, o = frames[i3]
    centre4 = frames[names.index("S4")]
    checked = 0
    for q, (x, y) in enumerate(xy):
        h = 1e-6
        z = tr.sag_numpy(i3, np.array([x, x + h, x - h, x, x]), np.array([y, y, y, y + h, y - h]))
        zx, zy = (z[1] - z[2]) / (2 * h), (z[3] - z[4]) / (2 * h)
        n = R @ (np.array([-zx, -zy, 1.0]) / np.sqrt(1 + zx * zx + zy * zy))
        P = R @ np.array([x, y, z[0]]) + o
        # into the glass: towards the exit face S4's aperture centre
        a4 = d.system.surfaces[names.index("S4")].aperture
        c4 = centre4[0] @ np.array([a4.decenter[0], a4.decenter[1],
                                    float(tr.sag_numpy(names.index("S4"), np.array([a4.decenter[0]]),
                                                       np.array([a4.decenter[1]]))[0])]) + centre4[1]
        u = n if n @ (c4 - P) > 0 else -n
        hits = [t for b in (names.index("S2"), names.index("S4"))
                if (t := _root_distance(tr, frames, b, P, u)) is not None]
        want = min(hits) if hits else np.inf
        got = th[0, q0 + q]
        if np.isfinite(want):
            assert got == pytest.approx(want, abs=1e-7), (x, y)
            checked += 1
        else:
            assert np.isinf(got)
    assert checked >= 20


def test_prism_thickness_blocks_are_independent(freeform):
    """Several parameter vectors in one launch give each vector's own thickness."""
    d, tr, v = freeform
    j = tr.index["S3.position_y"]
    V = np.repeat(v[None], 3, axis=0)
    V[1, j] += 0.5
    V[2, j] -= 0.5
    th3, _ = solids.prism_thickness(tr, V, points=5)
    for b in range(3):
        th1, _ = solids.prism_thickness(tr, V[b], points=5)
        np.testing.assert_array_equal(th1[0], th3[b])
    assert not np.array_equal(th3[1], th3[2])
