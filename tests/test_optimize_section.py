"""The [optimize] section: parsed into OptimizeSpec, every bad value named in one line."""

import math
import re
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
    # drop from "[optimize]" up to the next table that is not an [optimize.*] table or
    # a [[optimize.stages]] entry
    return re.sub(r"(?ms)^\[\[?optimize(\.[a-z.]+)?\]\]?\n.*?(?=^\[(?!\[?optimize))", "", text)


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
    ('solver = "bfgs"', "optimize.solver", "lm, lm-hinge, adam"),
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
    ("[optimize.targets]\nfov_deg = [30.0]", "optimize.targets.fov_deg", "[x, y]"),
    ("[optimize.targets]\nfov_deg = [30.0, 190.0]", "optimize.targets.fov_deg", "(0, 180)"),
    ("[optimize.targets]\npixel_arcmin = 3.0", "optimize.targets.pixel_arcmin", "[x, y]"),
    ("[optimize.targets]\npixel_arcmin = [3.0, -1.0]", "optimize.targets.pixel_arcmin", "(0, 600)"),
    ("[optimize.targets]\ndisplay_mismatch_max = 1.5", "optimize.targets.display_mismatch_max", "[0, 1]"),
    ("[optimize.targets]\ndisplay_mismatch_max = true", "optimize.targets.display_mismatch_max", "[0, 1]"),
    ("[optimize.targets]\nfootprint_max_mm = 0.0", "optimize.targets.footprint_max_mm", "> 0"),
    ("[optimize.targets]\nfootprint_max_mm = \"1.5\"", "optimize.targets.footprint_max_mm", "a number"),
    ("[optimize.targets]\nspot = 1.0", "optimize.targets.spot", "unknown key"),
    ("[optimize.targets]\ntrack_max_mm = -150.0", "optimize.targets.track_max_mm", "> 0"),
    ("[optimize.targets]\neye_relief_min_mm = 0.0", "optimize.targets.eye_relief_min_mm", "> 0"),
    ("[optimize.targets]\nbox_max_mm = [50.0, 50.0]", "optimize.targets.box_max_mm", "[x, y, z]"),
    ("[optimize.targets]\nprism_box_max_mm = [40.0, 0.0, 40.0]", "optimize.targets.prism_box_max_mm", "positive"),
    ('[optimize.targets]\ntunable_aperture_mm = "10"', "optimize.targets.tunable_aperture_mm", "number"),
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


SCHEDULE = """
[optimize]
variables = [{ name = "S1.curvature", min = -0.05, max = 0.05 }, "S3.x2y0", "tunable"]
iterations = 7
[optimize.sampling]
stride = [4, 2]
pupil = 3
[optimize.targets]
gd_max_deg = 0.6
pa_max = 0.3
[optimize.weights]
gd = 4.0
[[optimize.stages]]
name = "coarse"
variables = ["S1.curvature", { name = "S3.x0y2", min = -1.0 }]
[[optimize.stages]]
name = "fine-1"
iterations = 3
stride = [1, 1]
solver = "adam"
[optimize.stages.targets]
gd_mean_deg = 0.2
[optimize.stages.weights]
gd = 32.0
"""


def test_schedule_parses_with_the_section_as_default(make_design, freeform_text):
    """Each [[optimize.stages]] entry takes the section's settings where it says nothing;
    its targets and weights replace only the keys it names; a bare variable name keeps
    the section's bounds."""
    o = make_design(freeform_text + SCHEDULE).optimize
    assert o.stages == ("coarse", "fine-1") and len(o.schedule) == 2
    a, b = o.schedule
    assert a.variables == (Variable("S1.curvature", -0.05, 0.05), Variable("S3.x0y2", -1.0, math.inf))
    assert (a.iterations, a.stride, a.pupil, a.fields, a.solver) == (7, (4, 2), 3, 3, "lm")
    assert a.targets == o.targets and a.weights == o.weights
    assert b.variables == o.variables and b.variables[2].lower == -5.0  # "tunable": the lens's range
    assert (b.iterations, b.stride, b.solver) == (3, (1, 1), "adam")
    assert (b.targets.gd_mean_deg, b.targets.gd_max_deg, b.weights.gd, b.weights.pa) == (0.2, 0.6, 32.0, 1.0)
    sub = o.for_stage(b)
    assert sub.variables == b.variables and sub.targets == b.targets and sub.schedule is None


STAGE_HEAD = 'variables = ["S1.curvature"]\n'
BAD_SCHEDULE = [
    ('[[optimize.stages]]\niterations = 3', "optimize.stages[0].name", "required"),
    ('[[optimize.stages]]\nname = "a b"', "optimize.stages[0].name", "letters, digits"),
    ('[[optimize.stages]]\nname = "a"\n[[optimize.stages]]\nname = "a"', "optimize.stages[1].name", "duplicate"),
    ('[[optimize.stages]]\nname = "a"\nsteps = 3', "optimize.stages[0].steps", "unknown key"),
    ('[[optimize.stages]]\nname = "a"\niterations = 0', "optimize.stages[0].iterations", ">= 1"),
    ('[[optimize.stages]]\nname = "a"\nstride = [1]', "optimize.stages[0].stride", "two integers"),
    ('[[optimize.stages]]\nname = "a"\nfields = 2', "optimize.stages[0].fields", "odd"),
    ('[[optimize.stages]]\nname = "a"\nsolver = "sgd"', "optimize.stages[0].solver", "lm, lm-hinge, adam"),
    ('[[optimize.stages]]\nname = "a"\nvariables = ["S1.curvatur"]', "optimize.stages[0].variables[0]",
     "S1.curvature"),
    ('[[optimize.stages]]\nname = "a"\nvariables = []', "optimize.stages[0].variables", "vary nothing"),
    ('[[optimize.stages]]\nname = "a"\n[optimize.stages.targets]\npa_max = -1.0',
     "optimize.stages[0].targets.pa_max", "> 0"),
    ('[[optimize.stages]]\nname = "a"\n[optimize.stages.weights]\nsharp = 1.0',
     "optimize.stages[0].weights.sharp", "unknown key"),
    ('full_iterations = 2\n[[optimize.stages]]\nname = "a"', "optimize.full_iterations", "per stage"),
]


@pytest.mark.parametrize("body,key,fragment", BAD_SCHEDULE)
def test_bad_schedule_entries_name_the_key(make_design, freeform_text, body, key, fragment):
    with pytest.raises(DesignError) as e:
        make_design(freeform_text + "\n[optimize]\n" + STAGE_HEAD + body + "\n", name="free.toml")
    assert e.value.key == key, str(e.value)
    assert "free.toml" in str(e.value) and fragment in str(e.value) and "\n" not in str(e.value)


def test_bad_schedule_entry_exits_2_naming_the_key(freeform_text, tmp_path, capsys):
    from lfsim.cli import main

    p = tmp_path / "free.toml"
    p.write_text(freeform_text + "\n[optimize]\n" + STAGE_HEAD + '[[optimize.stages]]\nname = "a"\nstride = [0, 1]\n')
    assert main(["optimize", str(p), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "optimize.stages[0].stride" in err and "free.toml" in err and not (tmp_path / "o").exists()
    p.write_text(freeform_text + "\n[optimize]\n" + STAGE_HEAD + '[[optimize.stages]]\nname = "a"\n')
    assert main(["optimize", str(p), "--out", str(tmp_path / "o"), "--stages", "b"]) == 2
    assert "--stages" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_package_limits_parse(make_design, freeform_text):
    d = make_design(freeform_text + "\n[optimize]\n[optimize.targets]\ntrack_max_mm = 150\n"
                    "box_max_mm = [50, 50.0, 160]\nprism_box_max_mm = [40.0, 40.0, 40.0]\n"
                    "eye_relief_min_mm = 18.0\nclear_diameter_max_mm = 25.4\ntunable_aperture_mm = 10.0\n"
                    "[optimize.weights]\npackage = 3.0\n")
    t = d.optimize.targets
    assert (t.track_max_mm, t.box_max_mm, t.prism_box_max_mm) == (150.0, (50.0, 50.0, 160.0), (40.0, 40.0, 40.0))
    assert (t.eye_relief_min_mm, t.clear_diameter_max_mm, t.tunable_aperture_mm) == (18.0, 25.4, 10.0)
    assert t.package_limits and d.optimize.weights.package == 3.0
    from lfsim.design.optimize_section import OptimizeTargets
    assert not OptimizeTargets().package_limits


def test_colour_weight_needs_two_wavelengths(make_design, freeform_text):
    text = (freeform_text + "\n[optimize]\n[optimize.weights]\ncolour = 2.0\n"
            "[optimize.targets]\nlateral_colour_max_arcmin = 3.0\n")
    spec = make_design(text).optimize
    assert spec.weights.colour == 2.0 and spec.targets.lateral_colour_max_arcmin == 3.0
    assert OptimizeSpec().weights.colour == 0.0  # off by default
    one = re.sub(r"(?m)^wavelengths_nm = .*$", "wavelengths_nm = [587.5618]", text)
    with pytest.raises(DesignError) as e:
        make_design(one, name="mono.toml")
    assert e.value.key == "optimize.weights.colour" and "mono.toml" in str(e.value)
    assert "two or more" in str(e.value) and "\n" not in str(e.value)
