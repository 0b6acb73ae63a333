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


def _rx(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(math.radians(a)), math.sin(math.radians(a))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def test_compound_tilt_is_intrinsic_x_then_y_then_z(make_design):
    """docs/architecture.md, frame convention 2: R = Rx·Ry·Rz, i.e. about x, then the
    rotated y′, then the twice-rotated z″; about fixed axes the order would be z, y, x."""
    d = make_design("""
        [[surfaces]]
        name = "t"
        dummy = true
        tilt = [20.0, 35.0, 50.0]
        return_axis = false
        [[surfaces]]
        dummy = true
    """)
    R = d.tracer().frames_numpy()[0][0]
    np.testing.assert_allclose(R, _rx(20) @ _ry(35) @ _rz(50), atol=1e-15)
    # Intrinsic construction: rotate the axes step by step about their current selves.
    axes = np.eye(3)
    for axis, ang in ((0, 20.0), (1, 35.0), (2, 50.0)):
        k = axes[:, axis]
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        a = math.radians(ang)
        axes = (np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K) @ axes
    np.testing.assert_allclose(R, axes, atol=1e-15)
    assert not np.allclose(R, _rz(50) @ _ry(35) @ _rx(20), atol=1e-3)  # not the extrinsic x, y, z order


def test_decenter_of_a_global_position_surface_moves_along_its_tilted_axes(make_design):
    """Frame convention 3: origin = position + R·(dx, dy, 0)."""
    d = make_design("""
        [[surfaces]]
        name = "g"
        dummy = true
        global_position = [1.0, 2.0, 30.0]
        tilt = [0.0, 90.0, 0.0]
        decenter = [3.0, 0.0]
        [[surfaces]]
        dummy = true
    """)
    R, o = d.tracer().frames_numpy()[0]
    np.testing.assert_allclose(o, [1.0, 2.0, 30.0 - 3.0], atol=1e-14)  # tilted x = global −z
    np.testing.assert_allclose(o, np.array([1.0, 2.0, 30.0]) + R @ [3.0, 0.0, 0.0], atol=1e-15)


def test_return_axis_defaults_true_on_surfaces_and_false_on_coordinate_breaks(make_design):
    """Frame convention 4."""
    text = """
        [[surfaces]]
        {kind}
        tilt = [10.0, 0.0, 0.0]
        thickness = 5.0
        [[surfaces]]
        dummy = true
    """
    surf = make_design(text.format(kind="dummy = true"), "s.toml")
    brk = make_design(text.format(kind='type = "coordinate_break"'), "b.toml")
    assert surf.system.surfaces[0].return_axis and not brk.system.surfaces[0].return_axis
    R1, o1 = surf.tracer().frames_numpy()[1]
    np.testing.assert_allclose(R1, np.eye(3), atol=1e-15)  # back on the original axis
    np.testing.assert_allclose(o1, [0, 0, 5], atol=1e-15)
    R1, o1 = brk.tracer().frames_numpy()[1]
    np.testing.assert_allclose(R1, _rx(10), atol=1e-15)  # the break's tilt carries on
    np.testing.assert_allclose(o1, _rx(10) @ [0, 0, 5], atol=1e-14)


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
