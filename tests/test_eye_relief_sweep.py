"""examples/eye_relief_sweep.py: the window moved to a chosen eye relief, apertures opened
within what their surfaces reach, and one re-optimization stage added that holds the eye relief."""

import importlib.util
import math
from pathlib import Path
from types import SimpleNamespace

import pytest

from lfsim.design import Design, load
from lfsim.design.errors import DesignError
from lfsim.ini.model import IniModel
from lfsim.ini.package import package

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("eye_relief_sweep", ROOT / "examples" / "eye_relief_sweep.py")
ers = importlib.util.module_from_spec(spec)
spec.loader.exec_module(ers)

BENCH = ROOT / "scenes" / "ini_freeform_optimized.toml"


def test_the_window_lands_at_the_eye_relief_asked_for():
    design = load(BENCH)
    e0 = package(IniModel(design), solids=False)["eye_relief_mm"]
    raw, opened = ers.moved(design, 22.5, ["S1", "S4", "TL"], 1.6, "balance", 5)
    got = Design.from_dict(raw, "moved")
    e = package(IniModel(got), solids=False)["eye_relief_mm"]
    assert abs(e0 - 17.5648) < 1e-3 and abs(e - 22.5) < 0.005
    # the window moved along its own line of sight: its tilt is unchanged
    vw = ers._surface_index(raw, raw["ini"]["viewing_window"], "moved")
    assert raw["surfaces"][vw]["tilt"] == design.raw["surfaces"][vw]["tilt"]
    # S4 (radius 21.6 mm) cannot open 1.6x: capped at 98 % of its reach; S1 and TL open fully
    assert opened["S1"] == 1.6 and opened["TL"] == 1.6 and 1.0 < opened["S4"] < 1.6
    s4 = raw["surfaces"][ers._surface_index(raw, "S4", "moved")]
    assert math.isclose(ers._reach(s4["aperture"], 1.0), 0.98 * abs(s4["radius"]), rel_tol=1e-9)
    # the added stage: the balance stage's targets and weights, lm-hinge, the eye relief held
    st = raw["optimize"]["stages"][-1]
    assert st["name"] == "sweep" and st["solver"] == "lm-hinge" and st["iterations"] == 5
    assert st["targets"]["eye_relief_min_mm"] == 22.5 and st["weights"]["package"] == 40.0
    assert st["weights"]["gd"] == 128.0 and st["targets"]["pa_max"] == 0.27
    # the source design's table is untouched
    assert "sweep" not in [s["name"] for s in design.raw["optimize"]["stages"]]


def test_reach_of_scaled_apertures():
    assert ers._reach({"radius": 2.0, "decenter": [3.0, 4.0]}, 1.5) == 3.0 + 5.0
    assert ers._reach({"half_width": [1.0, 2.0], "decenter": [0.0, -1.0]}, 2.0) == math.hypot(2.0, 5.0)
    for ap in ({"radius": 2.0, "decenter": [3.0, 4.0]}, {"half_width": [1.0, 2.0], "decenter": [0.5, -1.0]}):
        f = ers._reach_factor(ap, 9.0)
        assert f > 1.0 and math.isclose(ers._reach(ap, f), 9.0, rel_tol=1e-12)


def test_bad_names_are_refused():
    design = load(BENCH)
    with pytest.raises(ValueError, match="--open 'S9': .* has no surface of that name"):
        ers.moved(design, 20.0, ["S9"], 1.6, "balance", 5)
    with pytest.raises(ValueError, match="--like 'polish': .* no optimization stage of that name "
                                         r"\(it has coarse, freeform, balance, full\)"):
        ers.moved(design, 20.0, ["S1"], 1.6, "polish", 5)
    # a window placed without a global position cannot be moved along its line of sight
    # (checked before anything is traced: a stand-in with the table is enough)
    raw = dict(design.raw, surfaces=[dict(s) for s in design.raw["surfaces"]])
    del raw["surfaces"][-1]["global_position"]
    with pytest.raises(DesignError, match=r"no_gp.toml: surfaces\[20\].global_position = None \(surface 'VW'\)"):
        ers.moved(SimpleNamespace(raw=raw, path="no_gp.toml"), 20.0, ["S1"], 1.6, "balance", 5)


def test_the_command_line_refuses_bad_numbers(capsys):
    with pytest.raises(SystemExit) as e:
        ers.main(["--out", "unused", "--eye-relief", "20,x"])
    assert e.value.code == 2 and "--eye-relief" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        ers.main(["--out", "unused", "--open-factor", "0.5"])
    assert e.value.code == 2 and "--open-factor = 0.5" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        ers.main(["--out", "unused", "--stride", "4.5,2"])
    assert e.value.code == 2 and "--stride = '4.5,2'" in capsys.readouterr().err
