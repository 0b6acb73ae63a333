"""Frames: tilts, decenters, coordinate breaks, global placement, apertures."""

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lfsim.optics.tracer import Status


def test_fold_mirror_with_coordinate_break(make_design):
    # 45° fold mirror; the following break turns the axis onto the reflected
    # beam, which then runs along the frame's -z (negative thickness).
    d = make_design("""
        [[surfaces]]
        name = "fold"
        mirror = true
        tilt = [45.0, 0.0, 0.0]
        return_axis = false
        [[surfaces]]
        type = "coordinate_break"
        tilt = [45.0, 0.0, 0.0]
        thickness = -10.0
        [[surfaces]]
        dummy = true
    """)
    r = d.trace(np.array([[0.0, 0.0, -5.0], [0.3, 0.2, -5.0]]), np.array([[0.0, 0.0, 1.0]] * 2))
    assert r.status.tolist() == [0, 0]
    np.testing.assert_allclose(r.directions, [[0, 1, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(r.positions[0], [0, 10, 0], atol=1e-13)
    np.testing.assert_allclose(r.positions[1], [0.3, 10, 0.2], atol=1e-13)  # mirror plane z = y


def test_decenter_then_tilt_and_return_axis(make_design):
    # A flat dummy surface decentered by 2 in y and tilted 30° about x, at z = 5;
    # with return_axis the next surface is back on the original axis at z = 8.
    d = make_design("""
        [[surfaces]]
        dummy = true
        thickness = 5.0
        [[surfaces]]
        name = "t"
        dummy = true
        decenter = [0.0, 2.0]
        tilt = [30.0, 0.0, 0.0]
        thickness = 3.0
        [[surfaces]]
        dummy = true
    """)
    r = d.trace(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0]]), record=True)
    # The tilted plane passes through (0, 2, 5) with normal Rx(30°)·z = (0, -sin30, cos30).
    n = np.array([0.0, -0.5, math.cos(math.radians(30))])
    hit = r.path[1, 0]
    assert abs(np.dot(hit - [0, 2, 5], n)) < 1e-14 and abs(hit[1]) < 1e-15
    np.testing.assert_allclose(r.positions[0], [0, 0, 8], atol=1e-14)
    fr = d.tracer().frames_numpy()
    np.testing.assert_allclose(fr[1][1], [0, 2, 5], atol=1e-15)
    np.testing.assert_allclose(fr[1][0][:, 2], n, atol=1e-15)


def test_global_position_and_same_as(make_design):
    d = make_design("""
        [[surfaces]]
        name = "a"
        radius = 50.0
        global_position = [0.0, 1.0, 10.0]
        tilt = [0.0, 10.0, 0.0]
        dummy = true
        [[surfaces]]
        thickness = 5.0
        dummy = true
        [[surfaces]]
        name = "again"
        same_as = "a"
        dummy = true
    """)
    fr = d.tracer().frames_numpy()
    np.testing.assert_allclose(fr[0][1], [0, 1, 10])
    np.testing.assert_allclose(fr[1][1], [0, 1, 10])  # follows the global frame, thickness 0
    np.testing.assert_allclose(fr[2][0], fr[0][0])
    np.testing.assert_allclose(fr[2][1], fr[0][1])
    assert "again.curvature" not in d.parameter_names()


def test_rectangular_and_decentered_apertures(make_design):
    d = make_design("""
        [[surfaces]]
        dummy = true
        aperture = { type = "rectangular", half_width = [2.0, 1.0], decenter = [0.5, 0.0] }
        thickness = 1.0
        [[surfaces]]
        dummy = true
    """)
    o = np.array([[2.4, 0.0, -1], [2.6, 0, -1], [-1.4, 0, -1], [-1.6, 0, -1], [0, 0.99, -1], [0, 1.01, -1]])
    r = d.trace(o, np.tile([0.0, 0.0, 1.0], (6, 1)))
    V = Status.VIGNETTED
    assert r.status.tolist() == [0, V, 0, V, 0, V]


def test_backend_refuses_old_libllvm_with_a_clear_message():
    old = Path("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1")
    if not old.exists():
        pytest.skip("no libLLVM 15 on this machine")
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=str(old), LFSIM_DEVICE="cpu")
    scene = Path(__file__).resolve().parents[1] / "scenes" / "cooke_triplet.toml"
    p = subprocess.run([sys.executable, "-m", "lfsim.cli", "first-order", str(scene), "--method", "parabasal"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "libLLVM 15" in p.stderr and "libllvm19" in p.stderr and "Traceback" not in p.stderr
