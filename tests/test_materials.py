"""Material catalog: formulas against printed catalog data and against optiland."""

import tomllib
import warnings
from importlib import resources

import numpy as np
import pytest

from lfsim.optics.materials import AIR, MaterialError, abbe, catalog, constant, lookup

REQUIRED = ["N-BK7", "F2", "SK16", "N-SF11", "PMMA", "PC", "E48R"]


def test_required_materials_present():
    cat = catalog()
    for name in REQUIRED:
        assert name.upper() in cat


def test_catalog_formulas_reproduce_printed_nd_vd():
    raw = tomllib.loads(resources.files("lfsim.optics").joinpath("data/materials.toml").read_text())
    checked = 0
    for name, entry in raw.items():
        if "nd_vd_source" in entry:  # nd/vd computed from the formula, nothing to check against
            continue
        m = lookup(name)
        assert abs(m.nd - entry["nd"]) < 5e-6, (name, m.nd, entry["nd"])
        assert abs(m.vd - entry["vd"]) < 0.01, (name, m.vd, entry["vd"])
        checked += 1
    assert checked >= 6


@pytest.mark.parametrize("name,ref", [("N-BK7", ("N-BK7", "schott")), ("F2", ("F2", "schott")),
                                      ("N-SF11", ("N-SF11", "schott")), ("SK16", ("SK16", None))])
def test_indices_match_optiland(name, ref):
    pytest.importorskip("optiland")
    from optiland.materials import Material

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        om = Material(ref[0], reference=ref[1]) if ref[1] else Material(ref[0])
        for lam in (450.0, 550.0, 650.0):
            ours = lookup(name).index(lam)
            theirs = float(np.ravel(om.n(lam / 1000.0))[0])
            assert abs(ours - theirs) < 1e-12, (name, lam, ours, theirs)


def test_simple_kinds():
    assert AIR.index(500.0) == 1.0
    assert constant(1.7).index([400.0, 700.0]).tolist() == [1.7, 1.7]
    m = abbe(1.6, 40.0)
    assert abs(m.nd - 1.6) < 1e-14 and abs(m.vd - 40.0) < 1e-10
    assert lookup("n-bk7") is lookup("N-BK7")
    with pytest.raises(MaterialError, match="unknown material 'XYZ'"):
        lookup("XYZ")
    with pytest.raises(MaterialError):
        abbe(1.5, -3)


def test_wavelength_outside_formula_range_is_a_design_error(make_design):
    from lfsim import DesignError

    with pytest.raises(DesignError, match="surfaces\\[0\\].material.*400-700 nm, not 1000 nm"):
        make_design("""
            [system]
            wavelengths_nm = [1000.0]
            [[surfaces]]
            radius = 10.0
            material = "SK16"
            thickness = 2
            [[surfaces]]
            dummy = true
        """)
