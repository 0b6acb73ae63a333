"""``--set KEY=VALUE`` overrides: parameter names, dotted paths, errors, and the CLI verbs."""

import json

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.design import DesignError
from lfsim.design.overrides import apply_overrides, load_with_overrides, parse_sets


def test_parameter_name_writes_the_files_own_words(scenes):
    path = scenes / "cooke_triplet.toml"
    base = lfsim.load(path)
    c0 = dict((n, v) for n, v, _ in base.system.parameter_table())["L1_front.curvature"]
    d = load_with_overrides(path, {"L1_front.curvature": c0 * 1.01, "L1_front.thickness": 3.5})
    table = {n: v for n, v, _ in d.system.parameter_table()}
    assert table["L1_front.curvature"] == pytest.approx(c0 * 1.01, rel=1e-15)
    assert table["L1_front.thickness"] == 3.5
    assert d.raw["surfaces"][0]["radius"] == pytest.approx(1 / (c0 * 1.01), rel=1e-15)
    # the first-order focal length moves: the override reaches the traced system
    assert d.first_order().efl != pytest.approx(base.first_order().efl, rel=1e-6)
    # the file's own table is untouched
    assert lfsim.load(path).raw == base.raw


def test_dotted_path_and_integer_kept(scenes):
    raw = lfsim.load(scenes / "ini_ideal.toml").raw
    out = apply_overrides(raw, {"ini.cdp_diopters[1]": 1.5})
    assert out["ini"]["cdp_diopters"][1] == 1.5 and raw["ini"]["cdp_diopters"][1] != 1.5
    if isinstance(raw["ini"].get("analysis", {}).get("fields"), int):
        out = apply_overrides(raw, {"ini.analysis.fields": 5.0})
        assert out["ini"]["analysis"]["fields"] == 5 and isinstance(out["ini"]["analysis"]["fields"], int)


@pytest.mark.parametrize("items, fragment", [
    (["L1_front.curvature"], "expected KEY=VALUE"),
    (["L1_front.curvature=abc"], "not a number"),
    (["L1_front.curvature=nan"], "not a number"),
    (["a=1", "a=2"], "given twice"),
])
def test_parse_errors(items, fragment):
    with pytest.raises(ValueError, match=fragment):
        parse_sets(items)


def test_unknown_key_names_file_key_value_and_close_matches(scenes):
    path = scenes / "cooke_triplet.toml"
    with pytest.raises(DesignError) as e:
        load_with_overrides(path, {"L1_front.curvatur": 0.05})
    msg = str(e.value)
    assert str(path) in msg and "L1_front.curvatur = 0.05" in msg and "L1_front.curvature" in msg
    assert "\n" not in msg
    with pytest.raises(DesignError, match="semi_diameter"):
        load_with_overrides(path, {"surfaces[0].semi_diameter": -5.0})


def test_cli_verbs_take_set(scenes, tmp_path, capsys):
    design = str(scenes / "cooke_triplet.toml")
    assert main(["params", design, "--set", "L1_front.thickness=3.5", "--json"]) == 0
    rows = {r["name"]: r["value"] for r in json.loads(capsys.readouterr().out)["params"]}
    assert rows["L1_front.thickness"] == 3.5
    assert main(["first-order", design, "--json"]) == 0
    efl0 = json.loads(capsys.readouterr().out)["efl"]
    assert main(["first-order", design, "--set", "L1_front.thickness=3.5", "--json"]) == 0
    efl1 = json.loads(capsys.readouterr().out)["efl"]
    assert np.isfinite(efl1) and efl1 != efl0
    assert main(["first-order", design, "--set", "nope=1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "nope = 1.0" in err and design in err


def test_missing_key_created_under_an_existing_table_then_validated(scenes):
    raw = lfsim.load(scenes / "ini_freeform.toml").raw
    out = apply_overrides(raw, {"ini.analysis.fields": 9})
    assert out["ini"]["analysis"]["fields"] == 9 and raw["ini"].get("analysis", {}).get("fields") != 9
    d = load_with_overrides(scenes / "ini_freeform.toml", {"ini.analysis.fields": 9})
    assert d.ini.fields == 9
    with pytest.raises(DesignError, match="fieldz"):
        load_with_overrides(scenes / "ini_freeform.toml", {"ini.analysis.fieldz": 9})
    with pytest.raises(DesignError, match="nosuch.analysis.fields = 9: a parameter name"):
        load_with_overrides(scenes / "ini_freeform.toml", {"nosuch.analysis.fields": 9})


def test_display_gap_is_a_parameter_of_the_design_vector(scenes, capsys):
    """``object.distance`` (the InI display gap g) is listed by ``lfsim params`` with
    every index filled at the primary wavelength, takes ``--set``, is written back
    into ``[object] distance`` and names a tolerance key; a lens with its object at
    infinity has no such entry."""
    from lfsim.design.tolerance_section import nominal_value
    from lfsim.optics.materials import lookup

    path = str(scenes / "ini_ideal.toml")
    assert main(["params", path, "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = {r["name"]: r["value"] for r in doc["params"]}
    assert rows["object.distance"] == 4.5 and doc["params"][-1]["name"] == "object.distance"
    assert all(isinstance(v, float) for v in rows.values())  # no null: indices are evaluated
    assert rows["object.index"] == pytest.approx(
        lookup("air").index(doc["wavelength_nm"]), rel=1e-15)
    assert main(["params", path, "--set", "object.distance=4.75", "--json"]) == 0
    rows = {r["name"]: r["value"] for r in json.loads(capsys.readouterr().out)["params"]}
    assert rows["object.distance"] == 4.75
    d = load_with_overrides(path, {"object.distance": 4.75})
    assert d.system.object_distance == 4.75 and d.raw["object"]["distance"] == 4.75
    assert nominal_value(d.raw, d.system, "object.distance") == 4.75
    assert "object.distance" not in lfsim.load(scenes / "cooke_triplet.toml").parameter_names()
    with pytest.raises(DesignError) as e:  # refused by the validation, named by the file it came from
        load_with_overrides(path, {"object.distance": -1.0})
    assert str(e.value).startswith(f"{path}: object.distance = -1.0")


@pytest.mark.parametrize("design,key,value", [
    ("cooke_triplet", "surfaces[2].thickness", 1.2),   # README: a dotted path into [[surfaces]]
    ("ini_freeform", "ini.analysis.fields", 5),        # README: a dotted path into [ini]
    ("ini_freeform", "S1.tilt_x", 0.1),                # README: the analyze example
    ("ini_coaxial", "L1.curvature", 0.6),
    ("ini_ideal", "MLA.power", 0.3),
    ("ini_freeform", "S3.x2y2", 0.03),
    ("ini_ideal", "TL.power", 0.002),
    ("ini_freeform", "mla.pitch_x", 1.01),
])
def test_every_readme_override_path_is_taken(scenes, design, key, value):
    """Each kind of --set key the README documents sets what it names."""
    path = scenes / f"{design}.toml"
    d = load_with_overrides(path, {key: value})
    table = {n: v for n, v, _ in d.system.parameter_table()}
    if key in table:
        assert table[key] == pytest.approx(value, rel=1e-12)
    elif key.startswith("surfaces["):
        assert d.system.surfaces[int(key[9:key.index("]")])].thickness == value
    else:
        assert d.raw["ini"]["analysis"]["fields"] == value and d.ini.fields == value
