"""Eye-lens camera (``lfsim_eye``) and the Arizona eye: checks against independent answers.

* the ideal eye (tangent mapping, focal plane) against Mitsuba's ``thinlens``;
* angular mapping and image orientation against a marker at a known angle;
* defocus blur against the closed form  D·|1/a − 1/b|  (rad);
* Arizona eye first-order data against a hand-written Gullstrand thick-lens
  computation and the model's published design properties;
* the accommodation solve against a brute-force 2-D pupil trace.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from lfsim.optics.materials import abbe
from lfsim.render import eye
from lfsim.render import eye_models as em

# Shared tiny-render helpers ----------------------------------------------


@pytest.fixture(scope="module")
def mi():
    return eye.register()


def _render(mi, sensor, shapes: dict, spp=None, seed=0, env=None):
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 2}, "sensor": sensor}
    scene.update(shapes)
    if env is not None:
        scene["env"] = {"type": "constant", "radiance": {"type": "rgb", "value": env}}
    sc = mi.load_dict(scene)
    img = mi.render(sc, spp=spp or 0, seed=seed)
    return np.array(img, dtype=np.float64)[..., 0]


def _pattern(mi, n=64):
    """An asymmetric texture (checker × ramps) so any flip or mirror would show."""
    y, x = np.mgrid[0:n, 0:n] / (n - 1)
    checker = ((np.floor(x * 8) + np.floor(y * 8)) % 2)
    img = 0.15 + 0.6 * checker * (0.3 + 0.7 * x) + 0.25 * y ** 2
    return mi.TensorXf(np.repeat(img[..., None], 3, axis=2).astype(np.float32))


def _textured_wall(mi, z, half=(300.0, 200.0), shift=(40.0, -25.0)):
    T = mi.ScalarTransform4f().translate([shift[0], shift[1], -z]).scale([half[0], half[1], 1.0])
    return {"type": "rectangle", "to_world": T,
            "emitter": {"type": "area", "radiance": {
                "type": "bitmap", "data": _pattern(mi), "raw": True, "filter_type": "bilinear"}}}


# 1. ideal eye vs Mitsuba's thinlens ----------------------------------------


def test_ideal_eye_matches_thinlens(mi):
    """Tangent mapping + focal plane = Mitsuba's thinlens, to noise level.

    thinlens looks along its local +z with +x = left and its aperture disk
    at the local origin; the eye looks along −z with +x = right, so the same
    camera is the eye frame rotated 180° about y. ``fov`` of thinlens is the
    horizontal full angle (fov_axis="x") with square pixels.
    """
    W, H, fov_x, pupil, focus, wall = 48, 36, 30.0, 6.0, 450.0, 800.0
    fov_y = eye.default_fov_y(fov_x, W, H, "tangent")
    spec = eye.EyeSpec(model="ideal", pupil_diameter_mm=pupil, focus_mm=focus,
                       fov_deg=(fov_x, fov_y), resolution=(W, H), mapping="tangent",
                       focus_surface="plane")

    def thinlens(seed):
        return {"type": "thinlens", "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 180.0),
                "aperture_radius": pupil / 2, "focus_distance": focus, "fov": fov_x,
                "fov_axis": "x", "near_clip": 1e-3,
                "film": {"type": "hdrfilm", "width": W, "height": H, "pixel_format": "rgb",
                         "rfilter": {"type": "box"}},
                "sampler": {"type": "independent", "sample_count": 32, "seed": seed}}

    shapes = lambda: {"wall": _textured_wall(mi, wall)}  # noqa: E731  (tensors are consumed)
    t0 = _render(mi, thinlens(0), shapes(), seed=0)
    t1 = _render(mi, thinlens(1), shapes(), seed=1)
    e2 = _render(mi, spec.sensor_dict(spp=32, seed=2), shapes(), seed=2)
    rmse_tt = np.sqrt(np.mean((t0 - t1) ** 2))
    rmse_et = np.sqrt(np.mean((e2 - t0) ** 2))
    ratio = rmse_et / rmse_tt
    print(f"thinlens: RMSE(eye, thin A)={rmse_et:.4g} RMSE(thin A, thin B)={rmse_tt:.4g} "
          f"ratio={ratio:.3f} means {e2.mean():.5f} / {t0.mean():.5f}")
    assert 0.7 < ratio < 1.5
    # The image is not trivially uniform (the comparison has content to lose).
    assert np.std(t0) > 5 * rmse_tt
    sem = np.std(t0 - t1) / math.sqrt(t0.size)
    assert abs(e2.mean() - t0.mean()) < 5 * sem + 1e-3 * t0.mean()


# 2. angular mapping and orientation ----------------------------------------


def _marker_shape(mi, z, ax_deg, ay_deg, radius, eye_to_world=None):
    """A bright disk facing the eye at visual angles (ax, ay), z mm in front of it."""
    x, y = z * math.tan(math.radians(ax_deg)), z * math.tan(math.radians(ay_deg))
    T = mi.ScalarTransform4f().translate([x, y, -z]).scale(radius)
    if eye_to_world is not None:
        T = mi.ScalarTransform4f(np.asarray(eye_to_world).tolist()) @ T
    return {"type": "disk", "to_world": T,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 100.0}}}


def _centroid(img):
    """Intensity centroid (col, row) in pixel-index units (the background is exactly 0)."""
    rows, cols = np.mgrid[0:img.shape[0], 0:img.shape[1]]
    return float(np.sum(cols * img) / img.sum()), float(np.sum(rows * img) / img.sum())


def _centroid_noise(mi, spec, shapes, c0, to_world=None):
    """Monte Carlo noise (px) of a 64-spp render's marker centroid ``c0``, from a second seed at
    16 spp (a quarter of the cost): Var(c16 − c64) = (4 + 1) Var(c64), so σ = |c16 − c64| / √5."""
    c1 = _centroid(_render(mi, spec.sensor_dict(to_world=to_world, spp=16, seed=1), shapes, seed=1))
    return float(np.max(np.abs(np.subtract(c0, c1)))) / math.sqrt(5)


def _centroid_tol(noise, separation):
    """0.25 px (the marker's own finite, slightly asymmetric image) or 4 x the centroid noise,
    whichever is larger; at most half the distance to the other mapping's answer (the ceiling
    that keeps noise from excusing the wrong mapping)."""
    tol = max(0.25, 4.0 * noise)
    assert tol < 0.5 * separation, (tol, noise, separation)
    return tol


def _moved_eye():
    """An eye frame translated and turned (30° about y, then 10° about x) in the scene."""
    def rot(axis, deg):
        c, s_ = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        R = np.eye(4)
        i, j = [(1, 2), (2, 0), (0, 1)][axis]
        R[i, i], R[i, j], R[j, i], R[j, j] = c, -s_, s_, c
        return R
    T = np.eye(4)
    T[:3, 3] = (15.0, -40.0, 120.0)
    return T @ rot(1, 30.0) @ rot(0, 10.0)


@pytest.mark.parametrize("model", ["ideal", "arizona"])
@pytest.mark.parametrize("moved", [False, True])
def test_marker_lands_at_its_visual_angle(mi, model, moved):
    """A small disk 10° right and 5° up lands on the pixel of that angle (row 0 = top).

    ``moved``: the eye sits elsewhere in the scene (``to_world`` a 4×4 array)
    and the marker is placed in the eye's frame, so the image must not change.
    """
    W, H, fov = 160, 120, (40.0, 30.0)
    ax, ay, z = 10.0, 5.0, 1000.0
    T = _moved_eye() if moved else None
    spec = eye.EyeSpec(model=model, pupil_diameter_mm=1.0 if model == "ideal" else 3.0,
                       focus_mm=z, fov_deg=fov, resolution=(W, H))
    img = _render(mi, spec.sensor_dict(to_world=T, spp=64),
                  {"m": _marker_shape(mi, z, ax, ay, 4.0, T)})
    col, row = _centroid(img)
    # Noise: the centroid of a second seed (~0.02 px at 64 spp).
    noise = _centroid_noise(mi, spec, {"m": _marker_shape(mi, z, ax, ay, 4.0, T)}, (col, row), to_world=T)
    # Pixel i covers [i, i+1): a visual angle maps to index u·W − 0.5.
    col_exp = (ax / fov[0] + 0.5) * W - 0.5
    row_exp = (0.5 - ay / fov[1]) * H - 0.5
    col_tan = (math.tan(math.radians(ax)) / math.tan(math.radians(fov[0] / 2)) + 1) / 2 * W - 0.5
    print(f"{model} (moved={moved}): marker at col {col:.3f} row {row:.3f}; expected {col_exp:.3f} {row_exp:.3f} "
          f"(tangent mapping would give col {col_tan:.3f})")
    assert col > W / 2 and row < H / 2  # right and up: right half, upper half
    tol = _centroid_tol(noise, abs(col_tan - col_exp))
    assert abs(col - col_exp) < tol and abs(row - row_exp) < tol, (col - col_exp, row - row_exp, tol, noise)
    assert abs(col_tan - col_exp) > 1.0  # the check can tell the mappings apart
    assert np.isfinite(img).all()


def test_tangent_mapping_marker(mi):
    W, H, fov = 160, 120, (40.0, 30.0)
    spec = eye.EyeSpec(pupil_diameter_mm=1.0, focus_mm=1000.0, fov_deg=fov, resolution=(W, H),
                       mapping="tangent")
    img = _render(mi, spec.sensor_dict(spp=64), {"m": _marker_shape(mi, 1000.0, -10.0, -5.0, 4.0)})
    col, row = _centroid(img)
    noise = _centroid_noise(mi, spec, {"m": _marker_shape(mi, 1000.0, -10.0, -5.0, 4.0)}, (col, row))
    t = math.tan(math.radians(10.0))
    col_exp = (-t / math.tan(math.radians(20.0)) + 1) / 2 * W - 0.5
    row_exp = (1 + math.tan(math.radians(5.0)) / math.tan(math.radians(15.0))) / 2 * H - 0.5
    col_equi = (-10.0 / fov[0] + 0.5) * W - 0.5  # where the equidistant mapping would put it
    tol = _centroid_tol(noise, abs(col_equi - col_exp))
    assert abs(col - col_exp) < tol and abs(row - row_exp) < tol, (col - col_exp, row - row_exp, tol, noise)


# 3. defocus blur -------------------------------------------------------------


def _edge_wall(mi, z):
    """Emitter covering x > 0 at distance z (a vertical edge through the axis)."""
    T = mi.ScalarTransform4f().translate([0.5 * z, 0.0, -z]).scale([0.5 * z, 0.5 * z, 1.0])
    return {"type": "rectangle", "to_world": T,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}


def _disk_esf(x, x0, R, L):
    """Edge spread of a uniform disk blur of radius R (the edge integral of the disk)."""
    t = np.clip((x - x0) / R, -1.0, 1.0)
    return L * (0.5 + (t * np.sqrt(1 - t * t) + np.arcsin(t)) / np.pi)


def test_defocus_blur_matches_closed_form(mi):
    """Blur diameter (rad) of an edge at b with focus at a is D·|1/a − 1/b|."""
    from scipy.optimize import curve_fit

    W, H = 200, 40
    fov = (1.0, 0.2)
    deg_per_px = fov[0] / W
    x = (np.arange(W) + 0.5) * deg_per_px - fov[0] / 2  # pixel-centre angles (deg)
    for pupil, a, b in ((4.0, 500.0, 1000.0), (3.0, 1000.0, 600.0)):
        spec = eye.EyeSpec(pupil_diameter_mm=pupil, focus_mm=a, fov_deg=fov, resolution=(W, H))
        fits = []
        for seed, spp in ((0, 64), (1, 16)):  # seed 1 (16 spp, a quarter of the cost) only measures the noise
            img = _render(mi, spec.sensor_dict(spp=spp, seed=seed), {"edge": _edge_wall(mi, b)}, seed=seed)
            fits.append(curve_fit(_disk_esf, x, img.mean(axis=0), p0=(0.0, 0.1, 1.0))[0])
        (x0, R, _), R1 = fits[0], fits[1][1]
        blur = math.radians(2 * R)
        expected = pupil * abs(1 / a - 1 / b)
        err = blur / expected - 1
        # Relative noise of the 64-spp fit: Var(R16 − R64) = (4 + 1) Var(R64) (~0.4 %).
        noise = abs(R - R1) / R / math.sqrt(5)
        print(f"defocus D={pupil} a={a} b={b}: blur {blur * 1e3:.4f} mrad, closed form "
              f"{expected * 1e3:.4f} mrad ({100 * err:+.2f} %, noise {100 * noise:.2f} %)")
        # 3 % (the disk model of the edge spread over box pixels) or 4 x the noise; ceiling 5 %.
        tol = max(0.03, 4.0 * noise)
        assert tol <= 0.05, (tol, noise)
        assert abs(err) < tol, (err, tol)
        assert abs(x0) < deg_per_px


# 4. Arizona eye: first-order data ------------------------------------------


def _gullstrand_power(A, lam):
    """Total power (D) by combining surface powers pairwise (thick-lens formula)."""
    rows = em.arizona_table(A)
    idx = [1.0] + [abbe(r.nd, r.vd).index(lam) for r in rows[:4]]

    def combine(P1, P2, t, n):  # Gullstrand: P = P1 + P2 − (t/n) P1 P2
        return P1 + P2 - t / n * P1 * P2

    Ps = [(idx[i + 1] - idx[i]) / (rows[i].radius * 1e-3) for i in range(4)]
    # Cornea (surfaces 0, 1) and lens (2, 3) as thick lenses, then combine via
    # their principal planes.
    def thick(i):
        P1, P2, t, n = Ps[i], Ps[i + 1], rows[i].thickness * 1e-3, idx[i + 1]
        P = combine(P1, P2, t, n)
        # principal planes from the vertices (m, reduced units)
        front = t / n * P2 / P * idx[i]
        back = -t / n * P1 / P * idx[i + 2]
        return P, front, back

    Pc, fc, bc = thick(0)
    Pl, fl, bl = thick(2)
    # Separation from the cornea's back principal plane to the lens's front one.
    gap = rows[1].thickness * 1e-3 - bc + fl
    return combine(Pc, Pl, gap, idx[2])


def test_arizona_first_order():
    """Power ≈ 60 D (unaccommodated), emmetropic at the d line, far point ≈ 1/A."""
    lam_d = 587.5618
    fo = em.arizona_first_order(0.0, lam_d)
    ref = _gullstrand_power(0.0, lam_d)
    print(f"Arizona A=0 d-line: power {fo.power_d:.4f} D (Gullstrand {ref:.4f} D), "
          f"EP {fo.ep_position:.4f} mm, EP mag {fo.ep_magnification:.4f}, far point {fo.far_point:.1f} mm")
    assert abs(fo.power_d - ref) < 1e-6
    assert abs(fo.power_d - 60.0) < 1.0
    for A in (1.0, 2.0, 4.0):
        assert abs(em.arizona_first_order(A, lam_d).power_d - _gullstrand_power(A, lam_d)) < 1e-6
    # Designed emmetropic (axial length 24 mm) at A = 0 …
    assert abs(1000.0 / fo.far_point) < 0.02
    # … and A is the accommodation in diopters, paraxially (far point from the cornea).
    for A in (1.0, 2.0):
        far = em.arizona_first_order(A, lam_d).far_point
        assert abs(-1000.0 / far - A) < 0.02 * A
    # Entrance pupil: ~3 mm behind the cornea, ~13 % larger than the iris.
    assert 2.8 < fo.ep_position < 3.2 and 1.08 < fo.ep_magnification < 1.18


# 5. accommodation solve --------------------------------------------------------


def _brute_rms(A, d, pupil, lam=550.0, n=161):
    """RMS spot (mm) by a square grid over the pupil, clipped by the real iris."""
    from lfsim.optics.tracer import SequentialTracer

    iris = em.iris_radius(pupil, A, lam)
    tr = SequentialTracer(em.arizona_system(A, iris_radius=iris), "float64")
    e0 = em.eye_origin_depth(lam)
    g = np.linspace(-0.6 * pupil, 0.6 * pupil, n)
    X, Y = [a.ravel() for a in np.meshgrid(g, g)]
    obj = np.array([0.0, 0.0, e0 - d])
    target = np.stack([X, Y, np.full_like(X, e0)], axis=1)
    import drjit as dr

    with dr.suspend_grad():
        out = tr.trace(tr.params(lam), tr.rays(np.tile(obj, (len(X), 1)), target - obj), clip=True)
    ok = np.asarray(out.status) == 0
    x, y = np.asarray(out.p[0])[ok], np.asarray(out.p[1])[ok]
    return float(np.sqrt(np.mean((x - x.mean()) ** 2 + (y - y.mean()) ** 2)))


def test_solve_accommodation():
    pupil = 3.0
    ds = [600.0, 750.0, 1000.0, 1400.0]
    As = [eye.solve_accommodation(d, pupil) for d in ds]
    print("A(d) at 3 mm, 550 nm: " + ", ".join(f"{d:g} mm → {A:.4f} D (1/d = {1000 / d:.4f})"
                                               for d, A in zip(ds, As)))
    for d, A in zip(ds, As):
        rms = em.axial_rms_spot(A, d, pupil)
        assert rms < em.axial_rms_spot(A + 0.1, d, pupil)
        assert rms < em.axial_rms_spot(A - 0.1, d, pupil)
        # The fast estimate (Gauss–Legendre, real iris edge) agrees with a brute-force grid.
        for dA in (0.0, 0.1):
            assert em.axial_rms_spot(A + dA, d, pupil) == pytest.approx(_brute_rms(A + dA, d, pupil),
                                                                         rel=0.03)
        # Documented: A ≠ 1/d (chromatic + spherical shift ≈ −0.25 … −0.4 D at 3 mm).
        assert 0.15 < 1000.0 / d - A < 0.5
    # Monotone in 1/d (As ordered by decreasing 1/d).
    assert all(a1 > a2 for a1, a2 in zip(As, As[1:]))
    assert eye.solve_accommodation(math.inf, pupil) < As[-1]
    # Paraxial criterion: the y-nu far point is at the distance.
    A_par = eye.solve_accommodation(1000.0, pupil, criterion="paraxial")
    far = em.arizona_first_order(A_par, 550.0).far_point
    assert far == pytest.approx(em.eye_origin_depth(550.0) - 1000.0, rel=1e-6)


# 6. Arizona renders ---------------------------------------------------------------


def test_arizona_brightness_matches_ideal(mi):
    """A uniform scene renders as its radiance (ideal eye: exactly) over a 60°×40° field."""
    for model in ("ideal", "arizona"):
        spec = eye.EyeSpec(model=model, focus_mm=1000.0, fov_deg=(60.0, 40.0), resolution=(24, 16))
        img = _render(mi, spec.sensor_dict(spp=512), {}, env=1.0)
        # Noise, from the image itself: the pixel-to-pixel spread (an upper bound on one pixel's
        # Monte Carlo noise, ~0.007 for the Arizona eye; 0 for the ideal eye) and its mean's
        # standard error, spread / sqrt(pixels) (~3e-4; a second seed scatters the mean by the same).
        pix = float(np.std(img))
        sem = pix / math.sqrt(img.size)
        print(f"{model}: uniform scene mean {img.mean():.4f} min {img.min():.4f} max {img.max():.4f} "
              f"(pixel noise {pix:.2g}, mean {sem:.2g})")
        assert np.isfinite(img).all()
        # Bounds: 1 % (mean) and 6 % (a corner pixel) of transmission the eye model may lose,
        # or 4 x the noise; ceilings 2 % and 10 %.
        tol_mean, tol_px = max(0.01, 4.0 * sem), max(0.06, 4.0 * pix)
        assert tol_mean <= 0.02 and tol_px <= 0.1, (sem, pix)
        assert abs(img.mean() - 1.0) < tol_mean
        # corners too (the exit-pupil disk covers the real pupil off axis)
        corners = img[[0, 0, -1, -1], [0, -1, 0, -1]]
        assert np.all(np.abs(corners - 1.0) < tol_px)


def _rise_width(prof):
    """10–90 % rise distance (pixels) of a rising edge profile."""
    lo, hi = np.median(prof[:10]), np.median(prof[-10:])
    p = (prof - lo) / (hi - lo)
    x = np.arange(len(p))
    x10 = np.interp(0.1, np.maximum.accumulate(p), x)
    x90 = np.interp(0.9, np.maximum.accumulate(p), x)
    return x90 - x10


def test_arizona_blur_smallest_at_solved_accommodation(mi):
    d, pupil = 1000.0, 3.0
    A = eye.solve_accommodation(d, pupil)
    widths, noise = {}, {}
    arcmin_per_px = 0.4 / 160 * 60
    for dA in (-0.1, 0.0, 0.1):
        spec = eye.EyeSpec(model="arizona", pupil_diameter_mm=pupil, accommodation_diopters=A + dA,
                           fov_deg=(0.4, 0.04), resolution=(160, 16))
        img = _render(mi, spec.sensor_dict(spp=64), {"edge": _edge_wall(mi, d)})
        assert np.isfinite(img).all()
        widths[dA] = _rise_width(img.mean(axis=0)) * arcmin_per_px  # arcmin
        # Noise of the width, from the render itself: the rows are independent samples of one
        # profile (box pixels), so the two halves' widths differ by about 2 x the full one's noise.
        noise[dA] = abs(_rise_width(img[::2].mean(axis=0)) - _rise_width(img[1::2].mean(axis=0))) \
            * arcmin_per_px / 2
    print(f"Arizona edge 10-90 % width (arcmin) at A*={A:.4f} ± 0.1 D: {widths} (noise {noise})")
    # The best focus is sharper by more than 4 x the noise of both widths compared (<= 0.04′ here).
    for dA in (-0.1, 0.1):
        assert widths[0.0] + 4.0 * math.hypot(noise[0.0], noise[dA]) < widths[dA], (widths, noise)
    # Defocus of 0.1 D over ~3 mm: blur diameter ≈ 0.3 mrad ≈ 1′; the 10–90 % rise
    # of a disk edge is ≈ 0.6 of the diameter. 4 x the noise is well inside that range.
    assert 4.0 * noise[0.1] < 0.3, noise
    assert 0.3 < widths[0.1] < 1.2


def test_arizona_sensor_reports_accommodation(mi):
    spec = eye.EyeSpec(model="arizona", focus_mm=750.0, pupil_diameter_mm=3.0,
                       fov_deg=(10.0, 10.0), resolution=(8, 8))
    s = spec.load(spp=4)
    assert s.accommodation == pytest.approx(eye.solve_accommodation(750.0, 3.0))
    assert spec.accommodation() == pytest.approx(s.accommodation)


# 7. bad input --------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, key", [
    (dict(pupil_diameter_mm=-1.0), "pupil_diameter_mm"),
    (dict(pupil_diameter_mm=0.0), "pupil_diameter_mm"),
    (dict(fov_deg=(0.0, 30.0)), "fov_deg[0]"),
    (dict(fov_deg=(40.0, 180.0)), "fov_deg[1]"),
    (dict(model="navarro"), "model"),
    (dict(mapping="fisheye"), "mapping"),
    (dict(focus_mm=-5.0), "focus_mm"),
    (dict(focus_mm=float("nan")), "focus_mm"),
    (dict(resolution=(0, 10)), "resolution"),
    (dict(model="ideal", accommodation_diopters=1.0), "accommodation_diopters"),
    (dict(wavelength_nm=-550.0), "wavelength_nm"),
])
def test_bad_input_names_the_key(kwargs, key):
    with pytest.raises(ValueError) as e:
        eye.EyeSpec(**kwargs)
    msg = str(e.value)
    assert key in msg and "\n" not in msg


def test_bad_plugin_property_and_solver_input(mi):
    with pytest.raises(Exception, match="pupil_diameter"):
        mi.load_dict({"type": "lfsim_eye", "pupil_diameter": -2.0})
    with pytest.raises(Exception, match="mapping"):
        mi.load_dict({"type": "lfsim_eye", "mapping": "fisheye"})
    with pytest.raises(ValueError, match="distance_mm"):
        eye.solve_accommodation(-100.0, 3.0)
    with pytest.raises(ValueError, match="pupil_diameter_mm"):
        eye.solve_accommodation(1000.0, 0.0)
    with pytest.raises(ValueError, match="criterion"):
        eye.solve_accommodation(1000.0, 3.0, criterion="mtf")
    with pytest.raises(ValueError, match="spp"):
        eye.EyeSpec().sensor_dict(spp=0)


def test_register_is_idempotent(mi):
    assert eye.register() is mi
    assert eye.register() is mi
