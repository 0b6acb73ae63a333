"""The [optimize] section: parsed into OptimizeSpec, every bad value named in one line."""

import math
from pathlib import Path

import pytest

import lfsim
from lfsim import DesignError
from lfsim.design.optimize_section import STAGES, OptimizeSpec, OptimizeTargets, Variable

EXAMPLE = """
[optimize]
variables = ["S3.x2y0", { name = "S1.curvature", min = -0.05, max = 0.05 },
             { name = "tunable", min = -2.0, max = 4.5 }, { name = "mla.pitch_y", max = 1.01 }]
solver = "adam"
iterations = 12
stages = ["relay_eyepiece", "full"]
[optimize.sampling]
stride = [2, 3]
fields = 5
pupil = 6
[optimize.targets]
gd_max_deg = 0.5
local_distortion_max = 0.04
crosstalk_margin = 0.01
efl_mm = nan
min_air_gap = 0.2
tir_margin_deg = 2.5
[optimize.weights]
spot = 2.0
efl = 0.0
"""


SCENES = Path(__file__).resolve().parents[1] / "scenes"


@pytest.fixture(scope="module")
def freeform_text():
    """scenes/ini_freeform.toml without its own [optimize] tables (the tests add theirs)."""
    import re

    text = (SCENES / "ini_freeform.toml").read_text()
    # drop from "[optimize]" up to the next table that is not an [optimize.*] table
    return re.sub(r"(?ms)^\[optimize(\.[a-z]+)?\]\n.*?(?=^\[(?!optimize))", "", text)


@pytest.fixture(scope="module")
def cooke_text():
    return (SCENES / "cooke_triplet.toml").read_text()


def test_example_section(make_design, freeform_text):
    d = make_design(freeform_text + EXAMPLE)
    o = d.optimize
    assert isinstance(o, OptimizeSpec)
    assert o.variables == (
        Variable("S3.x2y0", -math.inf, math.inf),
        Variable("S1.curvature", -0.05, 0.05),
        Variable("tunable", -2.0, 4.5),
        Variable("mla.pitch_y", -math.inf, 1.01),
    )
    assert o.variable_names == ("S3.x2y0", "S1.curvature", "tunable", "mla.pitch_y")
    assert o.variables[2].is_tunable and not o.variables[0].bounded and o.variables[3].bounded
    assert (o.solver, o.iterations, o.stages) == ("adam", 12, ("relay_eyepiece", "full"))
    assert (o.stride, o.fields, o.pupil) == ((2, 3), 5, 6)
    t = o.targets
    assert (t.gd_max_deg, t.pa_max, t.efl_mm) == (0.5, d.ini.pa_target, None)  # pa_max from [ini.analysis]
    assert (t.local_distortion_max, t.crosstalk_margin, t.min_air_gap, t.tir_margin_deg) == (0.04, 0.01, 0.2, 2.5)
    assert (t.min_center_thickness, t.min_edge_thickness, t.min_prism_thickness) == (0.3, 0.3, 1.0)
    assert (o.weights.spot, o.weights.efl, o.weights.gd, o.weights.tir) == (2.0, 0.0, 1.0, 1.0)
    with pytest.raises(AttributeError):
        o.solver = "lm"  # frozen


def test_defaults(make_design, freeform_text, cooke_text):
    assert make_design(freeform_text).optimize is None
    d = make_design(freeform_text + "\n[optimize]\nvariables = ['tunable']\n")
    o = d.optimize
    assert o.variables == (Variable("tunable", -5.0, 5.0),)  # [ini.tunable] range_diopters
    assert (o.solver, o.iterations, o.stages) == ("lm", 30, STAGES)
    assert (o.stride, o.fields, o.pupil) == ((4, 2), 3, 4)
    assert o.targets == OptimizeTargets(gd_max_deg=d.ini.gd_target_deg, pa_max=d.ini.pa_target)
    assert OptimizeTargets().resolve(d.ini) == o.targets and OptimizeTargets().gd_max_deg is None
    assert o.weights.efl == 10.0 and o.weights.spot == 1.0
    assert OptimizeSpec.default() == OptimizeSpec(variables=(), stages=STAGES)
    assert OptimizeSpec.default(ini=False).stages == ("full",)
    plain = make_design(cooke_text + "\n[optimize]\nvariables = ['L1_front.curvature']\n").optimize
    assert plain.stages == ("full",) and plain.targets == OptimizeTargets()


BAD = [
    ('variables = ["S3.x2y1", "S3.x2y0z"]', "optimize.variables[1]", "close matches: S3.x2y0"),
    ('variables = [{ name = "S1.curvatur" }]', "optimize.variables[0].name", "S1.curvature"),
    ('variables = [{ min = 0.0 }]', "optimize.variables[0].name", "required"),
    ('variables = [{ name = "S1.curvature", min = 0.1, max = 0.05 }]', "optimize.variables[0].max", "> min"),
    ('variables = [{ name = "S1.curvature", min = 0.05, max = 0.05 }]', "optimize.variables[0].max", "> min"),
    ('variables = [{ name = "S1.curvature", min = "low" }]', "optimize.variables[0].min", "expected a number"),
    ('variables = [{ name = "S1.curvature", lower = 0.0 }]', "optimize.variables[0].lower", "unknown key"),
    ('variables = ["S3.x2y0", { name = "S3.x2y0" }]', "optimize.variables[1].name", "duplicate"),
    ('variables = ["S1.conic", "S1.conic"]', "optimize.variables[1]", "duplicate"),
    ('variables = ["S1.index"]', "optimize.variables[0]", "materials"),
    ('variables = ["object.index"]', "optimize.variables[0]", "materials"),
    ('variables = [3]', "optimize.variables[0]", "a parameter name"),
    ('variables = "S1.curvature"', "optimize.variables", "a list"),
    ('variables = [{ name = "tunable", min = -6.0 }]', "optimize.variables[0].min", "range"),
    ('variables = [{ name = "tunable", max = 5.5 }]', "optimize.variables[0].max", "range"),
    ('variables = ["TL.power"]', "optimize.variables[0]", '"tunable"'),
    ('variables = ["TL.curvature"]', "optimize.variables[0]", "paraxial"),
    ('variables = ["L1.tilt_x"]', "optimize.variables[0]", "mla.center_x"),
    ('variables = ["VW.curvature"]', "optimize.variables[0]", "plane"),
    ('solver = "bfgs"', "optimize.solver", "lm, adam"),
    ("iterations = 0", "optimize.iterations", ">= 1"),
    ("iterations = 2.5", "optimize.iterations", "integer"),
    ("stages = []", "optimize.stages", "non-empty"),
    ('stages = ["full", "mla"]', "optimize.stages", "this order"),
    ('stages = ["mla", "mla"]', "optimize.stages[1]", "duplicate"),
    ('stages = ["integrate"]', "optimize.stages[0]", "did you mean 'integrated'"),
    ("method = 'lm'", "optimize.method", "unknown key"),
    ("[optimize.sampling]\nstride = [0, 1]", "optimize.sampling.stride", "integers >= 1"),
    ("[optimize.sampling]\nfields = 4", "optimize.sampling.fields", "odd"),
    ("[optimize.sampling]\npupil = 1", "optimize.sampling.pupil", ">= 2"),
    ("[optimize.sampling]\nrays = 3", "optimize.sampling.rays", "unknown key"),
    ("[optimize.targets]\ngd_max_deg = -1.0", "optimize.targets.gd_max_deg", "> 0"),
    ("[optimize.targets]\ncrosstalk_margin = 0.6", "optimize.targets.crosstalk_margin", "[0, 0.5)"),
    ("[optimize.targets]\nefl_mm = 0.0", "optimize.targets.efl_mm", "nonzero"),
    ("[optimize.targets]\ntir_margin_deg = 95.0", "optimize.targets.tir_margin_deg", "[0, 90)"),
    ("[optimize.targets]\nmin_air_gap = -0.1", "optimize.targets.min_air_gap", ">= 0"),
    ("[optimize.targets]\nspot = 1.0", "optimize.targets.spot", "unknown key"),
    ("[optimize.weights]\nspot = -1.0", "optimize.weights.spot", ">= 0"),
    ("[optimize.weights]\nefl = inf", "optimize.weights.efl", "finite"),
    ('[optimize.weights]\ngd = "high"', "optimize.weights.gd", "number"),
    ("[optimize.weights]\nsharpness = 1.0", "optimize.weights.sharpness", "unknown key"),
]


@pytest.mark.parametrize("body,key,fragment", BAD)
def test_bad_values_name_file_key_and_value(make_design, freeform_text, body, key, fragment):
    with pytest.raises(DesignError) as e:
        make_design(freeform_text + "\n[optimize]\n" + body + "\n", name="free.toml")
    assert e.value.key == key, str(e.value)
    assert "free.toml" in str(e.value) and fragment in str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("body,key,fragment", [
    ('variables = ["tunable"]', "optimize.variables[0]", "[ini.tunable]"),
    ('stages = ["mla", "full"]', "optimize.stages[0]", "[ini]"),
    ('variables = ["L1_front.curvature", "L2_front.tilt_x", "L2_back.curvatre"]', "optimize.variables[2]",
     "L2_back.curvature"),
])
def test_plain_lens_limits(make_design, cooke_text, body, key, fragment):
    with pytest.raises(DesignError) as e:
        make_design(cooke_text + "\n[optimize]\n" + body + "\n")
    assert e.value.key == key and fragment in str(e.value)


def test_section_must_be_a_table(tmp_path):
    p = tmp_path / "d.toml"
    p.write_text('optimize = 3\n[[surfaces]]\nradius = 20.0\nthickness = 3.0\n[[surfaces]]\ndummy = true\n')
    with pytest.raises(DesignError) as e:
        lfsim.load(p)
    assert e.value.key == "optimize"
