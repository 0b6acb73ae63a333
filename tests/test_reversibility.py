"""Tracing the exit ray backwards through the same surfaces returns the entrance ray."""

import numpy as np
import pytest
from helpers import reversed_system, trace_np
from test_gradients import FREEFORM

import lfsim
from lfsim.optics.tracer import SequentialTracer

FOLDED = """
[system]
aperture = { type = "epd", value = 4.0 }
[[surfaces]]
name = "L"
radius = 20.0
xy = { x2y0 = 0.01, x0y3 = 0.002, x2y1 = 0.001 }
norm_radius = 4.0
thickness = 5.0
material = "E48R"
tilt = [4.0, 0.0, 0.0]
[[surfaces]]
name = "M"
radius = -60.0
conic = -0.3
mirror = true
thickness = -4.0
tilt = [8.0, 1.0, 0.0]
decenter = [0.0, 0.5]
[[surfaces]]
name = "T"
radius = inf
tir = true
thickness = 6.0
tilt = [-38.0, 0.0, 0.0]
[[surfaces]]
name = "out"
radius = -30.0
thickness = 10.0
global_position = [0.0, 9.0, 0.0]
tilt = [-90.0, 0.0, 0.0]
[[surfaces]]
name = "image"
dummy = true
"""


def _roundtrip(system, o, d):
    fwd = SequentialTracer(system)
    p1, d1, st1, opl1 = trace_np(fwd, o, d)
    back = SequentialTracer(reversed_system(system, fwd.frames_numpy(), end_plane_z=o[0, 2]))
    p2, d2, st2, opl2 = trace_np(back, p1, -d1)
    return st1, st2, p2, d2, opl1, opl2


@pytest.mark.parametrize("design", ["cooke", "freeform"])
def test_reverse_trace_returns_the_entrance_ray(design, scenes, tmp_path):
    if design == "cooke":
        sysm = lfsim.load(scenes / "cooke_triplet.toml").system
    else:
        p = tmp_path / "ff.toml"
        p.write_text(FREEFORM)
        sysm = lfsim.load(p).system
    rng = np.random.default_rng(3)
    n = 200
    o = np.concatenate([rng.uniform(-3, 3, (n, 2)), np.full((n, 1), -2.0)], 1)
    ang = np.radians(rng.uniform(-8, 8, (n, 2)))
    d = np.stack([np.sin(ang[:, 0]), np.sin(ang[:, 1]), np.ones(n)], 1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    st1, st2, p2, d2, opl1, opl2 = _roundtrip(sysm, o, d)
    ok = (st1 == 0) & (st2 == 0)
    assert ok.mean() > 0.9
    assert np.max(np.abs(p2[ok] - o[ok])) < 1e-10
    assert np.max(np.abs(d2[ok] + d[ok])) < 1e-12
    assert np.max(np.abs(opl1[ok] - opl2[ok])) < 1e-10


def test_reverse_trace_through_mirror_and_tir(tmp_path):
    p = tmp_path / "folded.toml"
    p.write_text(FOLDED)
    sysm = lfsim.load(p).system
    g = np.linspace(-1.0, 1.0, 7)
    X, Y = np.meshgrid(g, g)
    o = np.stack([X.ravel(), Y.ravel(), np.full(X.size, -3.0)], 1)
    d = np.tile([0.0, 0.0, 1.0], (len(o), 1))
    st1, st2, p2, d2, opl1, opl2 = _roundtrip(sysm, o, d)
    assert np.all(st1 == 0), st1
    ok = st2 == 0
    assert ok.all(), st2
    assert np.max(np.abs(p2 - o)) < 1e-10
    assert np.max(np.abs(d2 + d)) < 1e-12
