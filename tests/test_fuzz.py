"""Property-based fuzzing of the design loader, the content loader and the CLI.

Bad input must end in a clear error (``DesignError`` from Python; exit status 2
and one line naming the file, key and value from ``lfsim``), never a traceback,
and nothing that loads may produce NaN. Generated inputs: malformed TOML (the
text of a good design cut, spliced or mangled), wrong types and nasty values
(zero, negative, huge, tiny, ±inf, NaN, empty lists, strings, tables) at any key
of three good designs (a lens, a lenslet array, an InI-HMD), unknown glasses,
semi-diameters beyond the surface's reach, element counts that do not fit the
display, and command lines with bad numbers or missing files.

Example counts: the default profile keeps the normal test run short (about
270 examples in all); ``LFSIM_FUZZ_EXAMPLES=N`` runs ``N`` examples per test
(``LFSIM_FUZZ_EXAMPLES=250 .venv/bin/python -m pytest tests/test_fuzz.py
--hypothesis-show-statistics`` runs more than 1000 in all), and ``-m slow`` adds
a run of 1000 generated designs.
"""

from __future__ import annotations

import copy
import json
import math
import os
import tomllib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import lfsim
from lfsim import DesignError
from lfsim.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
_N = os.environ.get("LFSIM_FUZZ_EXAMPLES")


def examples(default: int) -> settings:
    """Hypothesis settings: ``default`` examples, or ``LFSIM_FUZZ_EXAMPLES``."""
    return settings(max_examples=int(_N) if _N else default, deadline=None, derandomize=not _N,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large, HealthCheck.filter_too_much])


# ------------------------------------------------------------------ TOML out
def _toml_key(k: str) -> str:
    return json.dumps(k, ensure_ascii=False)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=True)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    raise TypeError(type(v))


def to_toml(data: dict) -> str:
    """TOML text of a table: every value inline (tomllib reads it back unchanged)."""
    return "".join(f"{_toml_key(k)} = {_toml_value(v)}\n" for k, v in data.items())


# --------------------------------------------------------------- base designs
LENS = """
[system]
aperture = { type = "epd", value = 8.0 }
field = { type = "angle", values = [0.0, 5.0] }
wavelengths_nm = [486.1327, 587.5618, 656.2725]
[[surfaces]]
radius = 20.0
thickness = 3.0
material = "N-BK7"
semi_diameter = 6.0
stop = true
[[surfaces]]
radius = -20.0
conic = -0.5
asphere = { A4 = 1e-5 }
thickness = 2.0
material = "F2"
semi_diameter = 6.0
[[surfaces]]
radius = inf
xy = { x2y0 = 1e-3, x0y2 = -2e-3, x0y3 = 1e-5 }
norm_radius = 6.0
thickness = 18.0
semi_diameter = 6.0
tilt = [1.0, 0.0, 0.0]
[[surfaces]]
dummy = true
"""

ARRAY = """
[system]
aperture = { type = "epd", value = 0.0 }
[object]
distance = 4.0
[arrays.mla]
m = 5
n = 3
pitch = [1.0, 0.8]
[[surfaces]]
radius = 1.5
thickness = 1.0
material = 1.5
array = "mla"
aperture = { type = "rectangular", half_width = [0.5, 0.4] }
[[surfaces]]
thickness = 5.0
array = "mla"
[[surfaces]]
dummy = true
"""

BASES = {
    "lens": tomllib.loads(LENS),
    "array": tomllib.loads(ARRAY),
    "ini": tomllib.loads((SCENES / "ini_ideal.toml").read_text()),
}


def test_toml_writer_round_trips():
    for data in BASES.values():
        assert tomllib.loads(to_toml(data)) == data


def _paths(obj, prefix=()):
    """Every key path of a nested table/array (tables, lists and leaves)."""
    out = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out.append(prefix + (k,))
            out += _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            out.append(prefix + (i,))
            out += _paths(v, prefix + (i,))
    return out


def _get(obj, path):
    for k in path:
        obj = obj[k]
    return obj


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


# ------------------------------------------------------------------ values
NASTY_FLOATS = st.sampled_from([0.0, -0.0, -1.0, 1e-300, -1e-300, 1e300, -1e300, math.inf, -math.inf,
                                math.nan, 0.5, 1.0, 2.0, 1e-9, 89.999999, 90.0, 360.0, 1e6, -1e6, 4.5])
NASTY_INTS = st.sampled_from([0, -1, 1, 2, 3, 7, 10**6, 2**62, -(2**62)])
NAMES = st.sampled_from(["", " ", "air", "AIR", "N-BK7", "UNOBTAINIUM", "inf", "-inf", "nan", "mla", "S1",
                         "VW", "TL", "epd", "fno", "na", "angle", "height", "paraxial", "coordinate_break",
                         "circular", "rectangular", "ideal", "x", "xy", "none", "x2y0", "A4", "ini_ideal.toml"])
SCALARS = st.one_of(NASTY_FLOATS, st.floats(width=64), NASTY_INTS, st.integers(-10**4, 10**4), st.booleans(),
                    NAMES, st.text(max_size=8))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(
    st.lists(inner, max_size=4),
    st.dictionaries(st.one_of(NAMES, st.sampled_from(["type", "value", "values", "radius", "half_width",
                                                      "nd", "vd", "n", "m", "pitch", "surface", "model"])),
                    inner, max_size=3)), max_leaves=6)


@st.composite
def mutated_design(draw):
    """(text, description): a base design with 1-3 structural mutations, or mangled text."""
    name = draw(st.sampled_from(sorted(BASES)))
    data = copy.deepcopy(BASES[name])
    how = draw(st.sampled_from(["replace", "replace", "perturb", "perturb", "delete", "add", "text"]))
    if how == "text":
        text = to_toml(data) if draw(st.booleans()) else (LENS if name == "lens" else ARRAY if name == "array"
                                                          else (SCENES / "ini_ideal.toml").read_text())
        for _ in range(draw(st.integers(1, 3))):
            i = draw(st.integers(0, len(text)))
            j = draw(st.integers(i, min(len(text), i + 12)))
            text = text[:i] + draw(st.sampled_from(["", "=", "[", "]", "{", "}", '"', "\n", ",", "[[", "#", ".",
                                                    "x", "1e", "\\", "\x00", "é"])) + text[j:]
        return text, f"{name}: mangled text"
    done = []
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(data)
        if how == "perturb":  # a number where a number belongs: the loader accepts more of these
            paths = [p for p in paths if _is_number(_get(data, p))]
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        parent = data
        for k in path[:-1]:
            parent = parent[k]
        key = path[-1]
        if how == "delete":
            if isinstance(parent, list) and len(parent) > 1:
                parent.pop(key)
            elif isinstance(parent, dict):
                parent.pop(key)
        elif how == "perturb":
            old = parent[key]
            parent[key] = draw(st.one_of(NASTY_FLOATS, st.floats(width=64), st.just(-old), st.just(old * 1e-9),
                                         st.just(old * 1e9), st.floats(-2.0, 2.0).map(lambda f: old * (1 + f))))
        elif how == "add" and isinstance(parent, dict):
            parent[draw(NAMES) or "extra"] = draw(VALUES)
        else:
            parent[key] = draw(VALUES)
        done.append(f"{how} {'.'.join(map(str, path))}")
    return to_toml(data), f"{name}: {'; '.join(done)}"


def _check_error(e: Exception, path: Path):
    msg = str(e)
    assert isinstance(e, DesignError), f"{type(e).__name__}: {msg}"
    assert "\n" not in msg and msg.startswith(str(path)), msg


def _check_finite(*arrays):
    for a in arrays:
        assert np.all(np.isfinite(a)), a


def _probe_rays(design):
    """A few rays along +z over the first surface's clear aperture (or 1 mm)."""
    s0 = design.surfaces[0]
    ext = s0.aperture.extent() if s0.aperture is not None else 1.0
    ext = ext if math.isfinite(ext) and 0 < ext < 1e6 else 1.0
    h = np.array([0.0, 0.3, -0.7, 0.95]) * ext
    z0 = -min(design.system.object_distance, 1.0)
    o = np.stack([0.2 * h, h, np.full(4, z0)], axis=1)
    return o, np.tile([0.0, 0.02, 1.0], (4, 1))


def _load_and_use(text: str, path: Path):
    """Load a design; if it loads, trace and (for an InI design) build its model: all finite."""
    from lfsim.ini.model import IniModel, IniModelError

    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    try:
        design = lfsim.load(path)
    except Exception as e:  # noqa: BLE001 - the point of the test
        _check_error(e, path)
        return "rejected"
    o, d = _probe_rays(design)
    for prec in ("float64", "float32"):
        r = design.trace(o, d, precision=prec)
        _check_finite(r.positions, r.directions, r.opl)
    fo = None
    try:
        fo = design.first_order()
    except ValueError as e:
        assert str(path) in str(e) and "\n" not in str(e), f"{type(e).__name__}: {e}"
    if fo is not None:
        for k, v in fo.as_dict().items():
            assert not (isinstance(v, float) and math.isnan(v)), (k, v)
    if design.ini is not None:
        try:
            model = IniModel(design)
        except (DesignError, IniModelError) as e:
            assert str(path) in str(e) and "\n" not in str(e), f"{type(e).__name__}: {e}"
            return "model rejected"
        for k in range(len(model.depths)):
            for key, v in model.state(k).as_dict().items():
                assert np.all(np.isfinite(v if v is not None else 0.0)), (key, v)
    return "loaded"


@examples(80)
@given(case=mutated_design())
def test_fuzz_design_loader(tmp_path, case):
    text, what = case
    _load_and_use(text, tmp_path / "fuzz.toml")


# ------------------------------------------------------------------ targeted
GLASSES = st.text(st.characters(codec="ascii", exclude_categories=("Cc",)), min_size=1, max_size=10)


@examples(10)
@given(glass=GLASSES, which=st.integers(0, 1))
def test_unknown_glass_names_the_surface(tmp_path, glass, which):
    from lfsim.optics.materials import catalog

    assume(glass.strip().upper() not in catalog() and glass.strip().lower() != "air")
    data = copy.deepcopy(BASES["lens"])
    data["surfaces"][which]["material"] = glass
    p = tmp_path / "glass.toml"
    p.write_text(to_toml(data))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == f"surfaces[{which}].material" and repr(glass)[:60] in str(e.value).replace("...", "")


@examples(10)
@given(pitch=st.one_of(st.floats(max_value=0.0), st.just(-0.0)), axis=st.integers(0, 1))
def test_zero_or_negative_pitch_is_rejected(tmp_path, pitch, axis):
    data = copy.deepcopy(BASES["array"])
    data["arrays"]["mla"]["pitch"][axis] = pitch
    p = tmp_path / "pitch.toml"
    p.write_text(to_toml(data))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == "arrays.mla.pitch" and "\n" not in str(e.value)


@examples(10)
@given(t=st.one_of(st.sampled_from([0.0, -0.0, -1e-12, -3.0, -1e6]), st.floats(-50.0, 0.0)),
       which=st.integers(0, 2))
def test_zero_or_negative_thickness_traces_finite_or_flags(tmp_path, t, which):
    """A glass element whose faces cross inside their apertures is refused with one line
    naming its thickness; marked ``virtual`` (deliberate geometry) it is traced, and rays
    are traced to finite values or flagged, never NaN."""
    data = copy.deepcopy(BASES["lens"])
    data["surfaces"][which]["thickness"] = t
    p = tmp_path / "t.toml"
    p.write_text(to_toml(data))
    if which == 0:  # the N-BK7 element (R 20 / −20): a thickness <= 0 crosses at the rim
        # (the F2 element's back face is tilted: pairs off one axis are not checked)
        with pytest.raises(DesignError) as e:
            lfsim.load(p)
        assert e.value.key == f"surfaces[{which}].thickness" and "cross" in str(e.value)
        assert "virtual = true" in str(e.value) and "\n" not in str(e.value)
        data["surfaces"][which + 1]["virtual"] = True
        p.write_text(to_toml(data))
    design = lfsim.load(p)
    o, d = _probe_rays(design)
    for prec in ("float64", "float32"):
        r = design.trace(o, d, precision=prec)
        _check_finite(r.positions, r.directions, r.opl)
        assert set(r.status.tolist()) <= {0, 1, 2, 3, 4}


@examples(10)
@given(frac=st.floats(1.0, 1e6, exclude_min=True), radius=st.sampled_from([-20.0, 20.0, 3.0, 0.5]),
       conic=st.sampled_from([0.0, -0.5, 2.0]))
def test_semi_diameter_beyond_the_surface_reach(tmp_path, frac, radius, conic):
    reach = abs(radius) / math.sqrt(1.0 + conic)
    data = copy.deepcopy(BASES["lens"])
    s = data["surfaces"][0]
    s.update(radius=radius, conic=conic, semi_diameter=reach * frac)
    p = tmp_path / "sd.toml"
    p.write_text(to_toml(data))
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == "surfaces[0].semi_diameter" and f"reaches only {reach:.6g} mm" in str(e.value)


# ------------------------------------------------------------------------ CLI
def _no_nan(text: str):
    def bad(c):
        raise AssertionError(f"non-finite number {c} in JSON output")

    return json.loads(text, parse_constant=bad)


def fresh(tmp_path) -> Path:
    """A new empty folder for one generated example (``tmp_path`` is shared by all of them)."""
    import tempfile

    return Path(tempfile.mkdtemp(dir=tmp_path))


def run_cli(argv, capsys):
    """(status, stdout, stderr) of ``lfsim argv``; argparse errors count as status 2."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def check_cli(rc, out, err, outputs=()):
    """Exit 0 with finite output, or exit 2 with one line on stderr and no output files."""
    assert rc in (0, 2), (rc, err)
    assert "Traceback" not in err and "JSON compliant" not in err, err
    if rc == 2:
        assert err.count("\n") == 1 and err.startswith("lfsim: error: "), err
        for p in outputs:
            p = Path(p)
            assert not p.exists() or (p.is_dir() and not any(p.rglob("*"))), f"{p} written on bad input"
    else:
        assert "nan" not in out.lower().replace("nanometre", ""), out


RAYS = st.lists(st.lists(st.sampled_from(["0", "1", "-1", "0.5", "-5", "1e300", "nan", "inf", "", "x", "1e-300"]),
                         min_size=5, max_size=7), min_size=0, max_size=3)


@examples(30)
@given(case=mutated_design(), rays=st.one_of(st.none(), RAYS), verb=st.sampled_from(["trace", "first-order", "ini"]),
       precision=st.sampled_from(["float64", "float32"]),
       wavelength=st.one_of(st.none(), st.sampled_from(["486.1327", "587.5618", "100", "1e9", "-3", "nan", "x"])))
def test_fuzz_cli_on_designs(tmp_path, capsys, case, rays, verb, precision, wavelength):
    text, _ = case
    tmp_path = fresh(tmp_path)
    design = tmp_path / "d.toml"
    design.write_text(text, encoding="utf-8", errors="surrogatepass")
    out = tmp_path / "out.csv"
    if verb == "trace":
        csv = tmp_path / "rays.csv"
        lines = ["x,y,z,dx,dy,dz", "0,0.5,-1,0,0,1", "0,-2,-1,0,0.01,1"] if rays is None else (
            ["x,y,z,dx,dy,dz"] + [",".join(r) for r in rays])
        csv.write_text("\n".join(lines) + "\n")
        argv = ["trace", design, "--rays", csv, "--precision", precision, "--out", out]
    elif verb == "first-order":
        argv = ["first-order", design, "--json"]
    else:
        argv = ["ini", design, "--json"]
    if wavelength is not None and verb != "ini":
        argv += ["--wavelength-nm", wavelength]
    rc, stdout, err = run_cli(argv, capsys)
    check_cli(rc, stdout, err, outputs=[out])
    if rc == 0 and verb != "trace":
        _no_nan(stdout)
    if rc == 0 and verb == "trace":
        assert "nan" not in out.read_text().lower()


NUM = st.one_of(st.sampled_from(["0", "-1", "1", "3", "3.5", "4.5", "15.75", "25", "31", "1e-300", "1e300",
                                 "inf", "-inf", "nan", "abc", "", "-3", "1e15", "28.5"]),
                st.floats(-100.0, 100.0).map(repr))
INI_FLAGS = ["--p-mla", "--g", "--l", "--f-mla", "--z-ic", "--d-mla-ep", "--cdp-diopters", "--z-xp", "--f-ep"]


@examples(30)
@given(values=st.fixed_dictionaries({}, optional={f: NUM for f in INI_FLAGS}),
       m=st.sampled_from(["17", "1", "0", "-2", "x", "1e3", None]), n=st.sampled_from(["9", "1", "0", None]),
       as_json=st.booleans())
def test_fuzz_cli_ini_first_order(capsys, values, m, n, as_json):
    argv = ["ini"]
    for k, v in values.items():
        argv += [k, v] if not v.startswith("-") else [f"{k}={v}"]
    if m is not None:
        argv += [f"--m={m}"]
    if n is not None:
        argv += [f"--n={n}"]
    if as_json:
        argv.append("--json")
    rc, out, err = run_cli(argv, capsys)
    check_cli(rc, out, err)
    if rc == 0 and as_json:
        d = _no_nan(out)
        assert all(v is None or not isinstance(v, float) or math.isfinite(v) for v in d.values())


@examples(25)
@given(p_mla=st.floats(1e-3, 1e3), g=st.floats(1e-3, 1e3), f_ep=st.floats(-1e3, 1e3).filter(lambda v: abs(v) > 1e-3),
       z_xp=st.floats(1e-3, 1e3), side=st.sampled_from(["l", "f_mla"]), mla=st.floats(-1e3, 1e3),
       eye=st.sampled_from(["z_ic", "cdp_diopters", "d_mla_ep"]), ev=st.floats(-1e3, 1e3))
def test_fuzz_first_order_equations_are_nan_free(p_mla, g, f_ep, z_xp, side, mla, eye, ev):
    """Eqs. (1)-(10) at any inputs: finite or infinite values (a limit), or IniInputError; no NaN."""
    from lfsim.ini import ini_first_order
    from lfsim.ini.first_order import IniInputError

    try:
        fo = ini_first_order(p_mla, g, f_ep, z_xp, 17, 9, **{side: mla, eye: abs(ev) if eye == "cdp_diopters" else ev})
    except IniInputError as e:
        assert "\n" not in str(e)
        return
    for k, v in fo.__dict__.items():
        assert not (isinstance(v, float) and math.isnan(v)), (k, fo)


FS_BAD = {
    "--spp": st.sampled_from(["0", "-4", "x", "1.5", ""]),
    "--focus-mm": st.sampled_from(["600,-1", "nan", "0", "a,b", "600,,700", "-inf"]),
    "--cdp-mm": st.sampled_from(["0", "-750", "nan", "abc", ""]),
    "--pupil-mm": st.sampled_from(["0", "-3", "nan", "inf", "x"]),
    "--resolution": st.sampled_from(["0,10", "10", "a,b", "10,-1", "1.5,2"]),
    "--tessellation": st.sampled_from(["0", "-1", "nan", "inf", "x"]),
    "--eye": st.sampled_from(["none", "", "Arizona"]),
    "--mla-cells": st.sampled_from(["baffled", ""]),
    "--optics": st.sampled_from(["meshes", ""]),
    "--seed": st.sampled_from(["x", "1.5", ""]),
    "--content": st.sampled_from(["missing.toml", "scenes", ""]),
    "design": st.sampled_from(["missing.toml", "scenes/cooke_triplet.toml", "scenes"]),
}
AN_BAD = {
    "--stride": st.sampled_from(["0,1", "1", "a,b", "-1,-1", "1.5,1"]),
    "--depths": st.sampled_from(["2.5", "nan", "x", "0,7", "inf"]),
    "--symmetry": st.sampled_from(["z", ""]),
    "--reference": st.sampled_from(["missing.toml", "scenes/cooke_triplet.toml"]),
    "design": st.sampled_from(["missing.toml", "scenes/cooke_triplet.toml", "scenes", ""]),
}


@examples(20)
@given(verb=st.sampled_from(["focal-stack", "analyze"]), data=st.data())
def test_fuzz_cli_bad_arguments_exit_2_and_write_nothing(tmp_path, capsys, verb, data):
    """One bad argument among good ones: exit 2, one line, no output files (nothing is rendered)."""
    table = FS_BAD if verb == "focal-stack" else AN_BAD
    bad = data.draw(st.lists(st.sampled_from(sorted(table)), min_size=1, max_size=3, unique=True))
    out = fresh(tmp_path) / "out"
    args = {"design": str(SCENES / "ini_ideal.toml"), "--out": str(out)}
    if verb == "focal-stack":
        args.update({"--content": str(SCENES / "fig9_wall.toml"), "--resolution": "8,6", "--spp": "1"})
    for k in bad:
        v = data.draw(table[k])
        args[k] = str(ROOT / v) if v.endswith((".toml", "scenes")) else v
    argv = [verb, args.pop("design")]
    for k, v in args.items():
        argv.append(f"{k}={v}")
    rc, stdout, err = run_cli(argv, capsys)
    assert rc == 2, (argv, rc, err)
    check_cli(rc, stdout, err, outputs=[out])


def test_inconsistent_display_size_exits_2(tmp_path, capsys):
    """17 × 9 elemental images of 1 mm need a 17 × 9 mm display; 50 px of 8 µm per EI make 6.8 × 3.6 mm."""
    data = tomllib.loads((SCENES / "ini_ideal.toml").read_text())
    data["ini"]["pixels_per_ei"] = [50, 125]
    p = tmp_path / "small_display.toml"
    p.write_text(to_toml(data))
    out = tmp_path / "fs"
    rc, stdout, err = run_cli(["focal-stack", p, "--content", SCENES / "fig9_wall.toml", "--spp", "1",
                               "--resolution", "8,6", "--out", out], capsys)
    assert rc == 2 and str(p) in err and "ini.pixels_per_ei = [50, 125]" in err and "17 x 9" in err, err
    check_cli(rc, stdout, err, outputs=[out])


@examples(15)
@given(ppe=st.tuples(st.integers(1, 400), st.integers(1, 400)), pitch=st.sampled_from([0.008, 0.004, 0.016]))
def test_display_size_check_matches_the_rule(scenes, ppe, pitch):
    """DisplayLayout accepts a display exactly when the EI mismatch at its edge is under half an EI."""
    from dataclasses import replace

    from lfsim.render.display import DisplayLayout

    model = _ideal_model(scenes)
    m = copy.copy(model)
    m.spec = replace(model.spec, pixels_per_ei=ppe, pixel_pitch=pitch)
    p_ei = model.ei_pitch(0)
    fits = all(n * abs(p_ei[i] - ppe[i] * pitch) <= p_ei[i] for i, n in enumerate((17, 9)))
    if fits:
        lay = DisplayLayout.from_model(m)
        assert (lay.width, lay.height) == (17 * ppe[0], 9 * ppe[1])
    else:
        with pytest.raises(DesignError, match=r"ini\.pixels_per_ei"):
            DisplayLayout.from_model(m)


_MODEL = {}


def _ideal_model(scenes):
    from lfsim.ini.model import model_at_depth

    if "ideal" not in _MODEL:
        _MODEL["ideal"] = model_at_depth(lfsim.load(scenes / "ini_ideal.toml"), 0.0)
    return _MODEL["ideal"]


CONTENT = (SCENES / "fig9_wall.toml").read_text()


@examples(30)
@given(data=st.data())
def test_fuzz_content_loader(tmp_path, data):
    from lfsim.content import load_content

    base = tomllib.loads(CONTENT)
    base["view"]["design"] = str(SCENES / "ini_ideal.toml")
    for _ in range(data.draw(st.integers(1, 3))):
        paths = _paths(base)
        if not paths:
            break
        path = data.draw(st.sampled_from(paths))
        parent = _get(base, path[:-1])
        if data.draw(st.booleans()) or not isinstance(parent, dict):
            parent[path[-1]] = data.draw(VALUES)
        else:
            parent.pop(path[-1])
    p = tmp_path / "content.toml"
    text = to_toml(base)
    if data.draw(st.integers(0, 5)) == 0:
        i = data.draw(st.integers(0, len(text)))
        text = text[:i] + data.draw(st.sampled_from(["[", "=", '"', "}", "\n"])) + text[i + 1:]
    p.write_text(text)
    try:
        c = load_content(p)
    except Exception as e:  # noqa: BLE001
        _check_error(e, p)
        return
    assert c.objects and all(np.all(np.isfinite(q.corners)) for q in c.objects)
    assert all(math.isfinite(v) for q in c.objects for v in q.radiance)


@pytest.mark.slow
@settings(max_examples=1000, deadline=None, derandomize=False,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                 HealthCheck.data_too_large, HealthCheck.filter_too_much])
@given(case=mutated_design())
def test_fuzz_thousand_designs(tmp_path, case):
    """1000 generated designs (slow): loaded, traced in both precisions and modelled, or refused clearly."""
    text, _ = case
    _load_and_use(text, tmp_path / "fuzz.toml")
