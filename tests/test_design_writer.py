"""Design writer: parameter values written into a design file and read back exactly."""

import copy
import math
import tomllib

import numpy as np
import pytest

import lfsim
from lfsim import DesignError
from lfsim.design.writer import apply_values, design_text, write_design

# (scene, [(parameter, new value as a function of the old one, raw key that changes)], tunable powers)
CASES = {
    "ini_coaxial.toml": (
        [
            ("L1.curvature", lambda v: v * 1.01, "surfaces[0].curvature"),
            ("L1.conic", lambda v: v + 0.01, "surfaces[0].conic"),
            ("L2.A4", lambda v: v * 1.02, "surfaces[1].asphere.A4"),
            ("L1.A6", lambda v: v * 0.98, "surfaces[0].asphere.A6"),
            ("F1a.curvature", lambda v: v * 1.005, "surfaces[3].radius"),
            ("A1b.thickness", lambda v: v + 0.1, "surfaces[6].thickness"),
            ("E1a.decenter_y", lambda v: 0.05, "surfaces[16].decenter"),
            ("E2a.tilt_x", lambda v: 0.5, "surfaces[19].tilt"),
            ("TL.power", lambda v: v * 1.01, "surfaces[10].focal_length"),
            ("mla.pitch_x", lambda v: 1.002, "arrays.mla.pitch"),
            ("mla.center_y", lambda v: 0.01, "arrays.mla.center"),
        ],
        [3.1, 2.4, 0.9],
    ),
    "ini_freeform.toml": (
        [
            ("S3.x2y0", lambda v: v * 1.01, "surfaces[18].xy.x2y0"),
            ("S1.x0y4", lambda v: v * 0.9, "surfaces[16].xy.x0y4"),
            ("S2.curvature", lambda v: v * 1.003, "surfaces[17].radius"),
            ("S4.conic", lambda v: -0.1, "surfaces[19].conic"),
            ("S1.position_y", lambda v: v + 0.01, "surfaces[16].global_position"),
            ("S2.tilt_x", lambda v: v + 0.05, "surfaces[17].tilt"),
            ("C1b.thickness", lambda v: v - 0.2, "surfaces[15].thickness"),
            ("mla.pitch_y", lambda v: 0.999, "arrays.mla.pitch"),
            ("TL.power", lambda v: v * 0.99, "surfaces[10].focal_length"),
            ("VW.position_z", lambda v: v + 0.3, "surfaces[20].global_position"),
        ],
        [4.5, 3.5, 1.5],
    ),
    "cooke_triplet.toml": (
        [
            ("L1_front.curvature", lambda v: v * 1.01, "surfaces[0].radius"),
            ("L3_back.curvature", lambda v: 0.0, "surfaces[5].radius"),
            ("image.curvature", lambda v: 0.001, "surfaces[6].radius"),
            ("L2_back.thickness", lambda v: v + 0.05, "surfaces[3].thickness"),
            ("L1_back.decenter_x", lambda v: 0.1, "surfaces[1].decenter"),
            ("L2_front.tilt_z", lambda v: 1.0, "surfaces[2].tilt"),
            ("L2_front.tilt_y", lambda v: -0.25, "surfaces[2].tilt"),
            ("L3_front.conic", lambda v: -0.5, "surfaces[4].conic"),
            ("L1_back.conic", lambda v: 0.3, "surfaces[1].conic"),
            ("L3_front.thickness", lambda v: v * 1.1, "surfaces[4].thickness"),
        ],
        None,
    ),
    "freeform_prism.toml": (
        [
            ("S1_tir.curvature", lambda v: 0.002, "surfaces[1].curvature"),  # same_as: the original S1
            ("S1.x2y0", lambda v: v * 1.05, "surfaces[1].xy.x2y0"),
            ("S2.position_z", lambda v: v + 0.02, "surfaces[2].global_position"),
            ("S3.tilt_x", lambda v: v - 0.1, "surfaces[4].tilt"),
            ("S2.x0y3", lambda v: v * 1.1, "surfaces[2].xy.x0y3"),
            ("display.decenter_y", lambda v: 0.2, "surfaces[5].decenter"),
            ("S1_tir.thickness", lambda v: 0.5, "surfaces[3].thickness"),
            ("S3.conic", lambda v: 0.2, "surfaces[4].conic"),
            ("pupil.position_x", lambda v: 0.01, "surfaces[0].global_position"),
            ("S2.curvature", lambda v: v * 0.98, "surfaces[2].radius"),
        ],
        None,
    ),
}


def _leaves(obj, prefix=""):
    """Flatten tables and arrays of tables to {dotted key: value}; number arrays are leaves."""
    out = {}
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.update(_leaves(v, f"{prefix}.{k}" if prefix else k))
    elif isinstance(obj, list) and obj and all(isinstance(v, dict) for v in obj):
        for i, v in enumerate(obj):
            out.update(_leaves(v, f"{prefix}[{i}]"))
    else:
        out[prefix] = obj
    return out


@pytest.mark.parametrize("scene", sorted(CASES))
def test_perturbed_design_round_trips(scenes, tmp_path, scene):
    design = lfsim.load(scenes / scene)
    raw_before = copy.deepcopy(design.raw)
    system = design.system
    lam = system.primary_wavelength_nm
    names = system.parameter_names()
    v0 = dict(zip(names, system.parameter_values(lam)))
    edits, tunable = CASES[scene]

    values, expected = {}, dict(v0)
    for name, change, _ in edits:
        canonical = "S1.curvature" if name == "S1_tir.curvature" else name
        values[name] = change(v0[canonical])
        expected[canonical] = values[name]
    raw = apply_values(design.raw, values, tunable)
    assert design.raw == raw_before  # the input table is not modified

    path = tmp_path / scene
    write_design(path, raw, ["lfsim test", f"perturbed copy of {scene}"])
    text = path.read_text()
    assert text.startswith("# lfsim test\n# perturbed copy of")
    assert tomllib.loads(text) == raw  # every float round-trips exactly (repr)
    assert [p.name for p in tmp_path.iterdir()] == [scene]  # no temporary file left

    back = lfsim.load(path)
    assert back.system.parameter_names() == names
    got = dict(zip(names, back.system.parameter_values(lam)))
    for n in names:
        if n in values or n == "S1.curvature" and "S1_tir.curvature" in values:
            assert got[n] == pytest.approx(expected[n], rel=1e-12, abs=1e-300), n
        else:
            assert got[n] == expected[n], n  # untouched parameters are bit-identical
    if tunable is not None:
        assert back.ini.tunable_power_diopters == tunable

    # Every other number of the file is unchanged.
    before, after = _leaves(raw_before), _leaves(back.raw)
    changed = {k for k in before.keys() | after.keys() if before.get(k, None) != after.get(k, None)}
    want = {key for _, _, key in edits} | ({"ini.tunable.power_diopters"} if tunable else set())
    assert changed == want


def test_radius_inf_and_curvature_spelling(scenes):
    raw = lfsim.load(scenes / "cooke_triplet.toml").raw
    out = apply_values(raw, {"L3_back.curvature": 0.0, "image.curvature": 0.004})
    assert math.isinf(out["surfaces"][5]["radius"]) and out["surfaces"][5]["radius"] > 0
    assert out["surfaces"][6]["radius"] == 250.0
    assert "radius = inf" in design_text(out, [])
    assert "curvature" not in out["surfaces"][5]


def test_unchanged_values_leave_the_table_as_is(scenes):
    for scene in ("ini_coaxial.toml", "freeform_prism.toml"):
        d = lfsim.load(scenes / scene)
        values = {n: v for n, v, _ in d.system.parameter_table() if not n.endswith(".index")}
        assert apply_values(d.raw, values) == d.raw


def test_write_design_replaces_atomically(tmp_path, scenes):
    raw = lfsim.load(scenes / "cooke_triplet.toml").raw
    path = tmp_path / "out" / "d.toml"
    write_design(path, raw, ["first"])
    write_design(path, apply_values(raw, {"L1_front.thickness": 3.5}), ["second", "", "multi\nline"])
    text = path.read_text()
    assert text.startswith("# second\n#\n# multi\n# line\n\n")
    assert tomllib.loads(text)["surfaces"][0]["thickness"] == 3.5
    assert sorted(p.name for p in path.parent.iterdir()) == ["d.toml"]


@pytest.mark.parametrize("scene,values,tunable,match", [
    ("cooke_triplet.toml", {"L1_front.curvatur": 0.05}, None, "close matches: L1_front.curvature"),
    ("cooke_triplet.toml", {"nowhere.thickness": 1.0}, None, "unknown parameter 'nowhere.thickness'"),
    ("cooke_triplet.toml", {"L1_front.index": 1.6}, None, "indices come from materials"),
    ("cooke_triplet.toml", {"object.index": 1.0}, None, "indices come from materials"),
    ("cooke_triplet.toml", {"L1_front.thickness": math.nan}, None, "not finite"),
    ("cooke_triplet.toml", {"L1_front.thickness": "thick"}, None, "not a number"),
    ("cooke_triplet.toml", {}, [1.0], r"no \[ini.tunable\]"),
    ("ini_coaxial.toml", {}, [1.0, 2.0], "one finite power"),
    ("ini_ideal.toml", {"TL.curvature": 0.01}, None, "paraxial"),
    ("freeform_prism.toml", {"S1.curvature": 0.001, "S1_tir.curvature": 0.002}, None, "one physical surface"),
])
def test_bad_values_are_refused(scenes, scene, values, tunable, match):
    raw = lfsim.load(scenes / scene).raw
    with pytest.raises(ValueError, match=match):
        apply_values(raw, values, tunable)


def test_result_that_is_not_a_design_is_refused(scenes):
    raw = lfsim.load(scenes / "cooke_triplet.toml").raw
    with pytest.raises(DesignError, match=r"surfaces\[0\].semi_diameter"):
        apply_values(raw, {"L1_front.curvature": 0.2})  # radius 5 mm under a 10 mm semi-diameter
    ini = lfsim.load(scenes / "ini_coaxial.toml").raw
    with pytest.raises(DesignError, match="lenslet surfaces"):
        apply_values(ini, {"L1.tilt_x": 1.0})


def test_values_accept_numpy_scalars(scenes):
    raw = lfsim.load(scenes / "cooke_triplet.toml").raw
    out = apply_values(raw, {"L1_front.thickness": np.float64(3.5)})
    assert type(out["surfaces"][0]["thickness"]) is float


def test_long_array_with_inline_tables_compacts_in_linear_time():
    """A variables list of 90 names with inline tables among them (an [optimize]
    section) used to send the flat-array pattern into exponential backtracking: the
    writer hung for hours (a regression hangs this test). The flat arrays around it
    are still put on one line."""
    names = [f"S{i % 4 + 1}.x{2 * (i % 3)}y{i % 5}" for i in range(80)]
    variables = names[:40] + [{"name": "R1b.thickness", "min": 1.5, "max": 12.0}] + names[40:]
    raw = {"optimize": {"variables": variables}, "surfaces": [{"name": "S1", "tilt": [0.0, 5.0, 0.0]}]}
    text = design_text(raw, ["header"])
    assert tomllib.loads(text) == raw
    assert "tilt = [0.0, 5.0, 0.0]" in text
