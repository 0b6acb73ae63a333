"""First-order optics: y-nu trace, parabasal AD route, folded and tilted systems."""

import math
from pathlib import Path

import numpy as np

import lfsim

TRIPLET = Path(__file__).resolve().parents[1] / "scenes" / "cooke_triplet.toml"


def folded_triplet(tmp_path, fold_at=20.0):
    text = TRIPLET.read_text()
    tail = text.rsplit("[[surfaces]]", 2)
    assert "L3_back" in tail[1]
    back = tail[1].replace("thickness = 42.20778", f"thickness = {fold_at}")
    folded = tail[0] + "[[surfaces]]" + back + f"""
[[surfaces]]
name = "fold"
mirror = true
tilt = [45.0, 0.0, 0.0]
return_axis = false
semi_diameter = 30.0

[[surfaces]]
type = "coordinate_break"
tilt = [45.0, 0.0, 0.0]
thickness = {-(42.20778 - fold_at)}

[[surfaces]]
name = "image"
dummy = true
"""
    p = tmp_path / "folded.toml"
    p.write_text(folded)
    return lfsim.load(p)


def test_fold_mirror_leaves_first_order_unchanged(tmp_path):
    ref = lfsim.load(TRIPLET).first_order().as_dict()
    folded = folded_triplet(tmp_path)
    fo = folded.first_order()
    assert fo.method == "parabasal"
    for k, v in ref.items():
        if k in ("bfl", "paraxial_image_distance"):
            v -= 20.0  # measured from the last surface before the image: now the fold mirror
        if isinstance(v, float):
            assert abs(fo.as_dict()[k] - v) < 1e-9 * max(1.0, abs(v)), (k, fo.as_dict()[k], v)


def test_folded_image_lies_where_the_fold_sends_it(tmp_path):
    folded = folded_triplet(tmp_path)
    r = folded.trace(np.array([[0.0, 0.0, -5.0]]), np.array([[0.0, 0.0, 1.0]]))
    z_fold = 3.25896 + 6.00755 + 0.99997 + 4.75041 + 2.95208 + 20.0
    np.testing.assert_allclose(r.positions[0], [0, 42.20778 - 20.0, z_fold], atol=1e-12)


def test_parabasal_matrix_equals_finite_parabasal_rays(tmp_path):
    """AD parabasal derivatives vs real rays offset by ±h about the axis ray."""
    text = TRIPLET.read_text().replace('name = "L2_front"',
                                       'name = "L2_front"\ntilt = [1.5, 0.8, 0.0]\ndecenter = [0.05, -0.1]')
    p = tmp_path / "tilted.toml"
    p.write_text(text)
    d = lfsim.load(p)
    from lfsim.optics.first_order import find_axis_ray, parabasal_matrices

    tr = d.tracer()
    lam = 587.5618
    Mx_f, Mx_t, My_f, My_t, n_o, n_i, t_last = parabasal_matrices(tr, lam)
    o0, d0 = find_axis_ray(tr, np.asarray(d.system.parameter_values(lam)), 3, 1.0, math.inf)
    assert abs(o0[0]) > 1e-4 or abs(o0[1]) > 1e-4  # the decentered element moves the axis ray
    h = 1e-5
    base = d.trace(o0[None], d0[None])
    plus = d.trace((o0 + [0, h, 0])[None], d0[None])
    minus = d.trace((o0 - [0, h, 0])[None], d0[None])
    # dy'/dy measured on the plane ⟂ the exit axis ray: approximate with the image-plane
    # intercept corrected for obliquity, to first order in h.
    dexit = base.directions[0]
    dp = (plus.positions[0] - minus.positions[0]) / (2 * h)
    dp -= np.dot(dp, dexit) * dexit
    e2 = np.array([0.0, 1.0, 0.0]) - dexit[1] * dexit
    e2 /= np.linalg.norm(e2)
    assert abs(np.dot(dp, e2) - My_t[0, 0]) < 1e-7
    assert abs(My_t[1, 0] + 1 / d.first_order().efl) < 1e-12


def _ideal_pair(tmp_path, f1, f2, d, mirror_first=False):
    """Two ideal lenses d apart (object at infinity), optionally met after a flat mirror
    (light then runs along −z, thicknesses negative)."""
    s = -1.0 if mirror_first else 1.0
    head = """
[[surfaces]]
name = "M"
mirror = true
thickness = -5.0
semi_diameter = 20.0
""" if mirror_first else ""
    text = f"""
[system]
aperture = {{ type = "epd", value = 4.0 }}
field = {{ type = "angle", values = [0, 2] }}
wavelengths_nm = [587.5618]
[object]
distance = inf
{head}
[[surfaces]]
name = "A"
type = "paraxial"
focal_length = {f1}
thickness = {s * d}
stop = true
[[surfaces]]
name = "B"
type = "paraxial"
focal_length = {f2}
thickness = {s * 30.0}
[[surfaces]]
name = "IMG"
dummy = true
"""
    p = tmp_path / "pair.toml"
    p.write_text(text)
    return lfsim.load(p)


def test_a_diverging_ideal_lens_keeps_its_sign_in_the_paraxial_trace(tmp_path):
    """Gullstrand: 1/f = 1/f1 + 1/f2 − d/(f1 f2); the y-nu trace, the real-ray parabasal
    route and the closed form agree, with the diverging lens first or second."""
    for f1, f2, d in ((-26.5219, 50.0, 10.0), (50.0, -26.5219, 10.0), (-40.0, -60.0, 5.0)):
        design = _ideal_pair(tmp_path, f1, f2, d)
        efl = 1.0 / (1.0 / f1 + 1.0 / f2 - d / (f1 * f2))
        par = design.first_order(method="paraxial").efl
        pb = design.first_order(method="parabasal").efl
        assert math.isclose(par, efl, rel_tol=1e-12), (f1, f2, par, efl)
        assert math.isclose(pb, efl, rel_tol=1e-9), (f1, f2, pb, efl)


def test_an_ideal_lens_after_a_mirror_keeps_its_power(tmp_path):
    """Light reflected by a flat mirror meets the same ideal lenses running along −z: the
    focal length is that of the unfolded pair, by both routes."""
    f1, f2, d = -26.5219, 50.0, 10.0
    efl = 1.0 / (1.0 / f1 + 1.0 / f2 - d / (f1 * f2))
    design = _ideal_pair(tmp_path, f1, f2, d, mirror_first=True)
    for method in ("paraxial", "parabasal"):
        assert math.isclose(abs(design.first_order(method=method).efl), abs(efl), rel_tol=1e-9), method
