"""examples/relay_variants.py: relay lenses swapped for ideal lenses or another glass keep the
design's paraxial matrix, so its InI first-order model (Eqs. 1-10 from the design's own maps)
is unchanged; only the aberrations differ."""

import importlib.util
import tomllib
from pathlib import Path

import numpy as np
import pytest
import tomli_w

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("relay_variants", ROOT / "examples" / "relay_variants.py")
rv = importlib.util.module_from_spec(spec)
spec.loader.exec_module(rv)

KEYS = ("tunable_power_diopters", "cdp_diopters_x", "cdp_diopters_y", "p_ei", "d_v", "D_v", "pixel_arcmin",
        "fov_deg")


@pytest.mark.parametrize("variant", ["ideal", "glass"])
def test_a_relay_variant_keeps_the_first_order(variant, tmp_path):
    # the start design: no tunable powers listed, so they are solved for each variant
    path = ROOT / "scenes" / "ini_wearable.toml"
    raw = tomllib.loads(path.read_text())
    tab = rv.ideal_relay(raw) if variant == "ideal" else rv.reglass_relay(raw, "N-LASF31A")
    p = tmp_path / f"{variant}.toml"
    p.write_text(tomli_w.dumps(tab))
    for a, b in zip(rv.first_order(path), rv.first_order(p)):
        for k in KEYS:
            assert np.allclose(np.atleast_1d(b[k]), np.atleast_1d(a[k]), rtol=0, atol=1e-6), (variant, k, a[k], b[k])
    kinds = [s.get("type") for s in tab["surfaces"] if s.get("name", "")[:2] in ("R1", "R2", "R3", "R4")]
    assert kinds == (["paraxial"] * 8 if variant == "ideal" else [None] * 8)


def test_a_relay_that_is_not_a_singlet_is_refused():
    raw = tomllib.loads((ROOT / "scenes" / "ini_wearable.toml").read_text())
    with pytest.raises(ValueError, match="R1b"):
        rv.ideal_relay(raw, ("R1b",))
    with pytest.raises(ValueError, match="no surface"):
        rv.reglass_relay(raw, "N-BK7", ("Q9",))


@pytest.mark.parametrize("argv, said", [
    (["--optimize", "bogus"], "--optimize 'bogus': 'bogus' is not a stage of ini_wearable.toml"),
    (["--glass", "NOPE"], "--glass 'NOPE': unknown material 'NOPE'"),
    (["--lenses", "R1a,R9a"], "no surface named 'R9a'"),
    (["--design", "TYPO"], "nmae"),
])
def test_bad_arguments_give_one_line_and_write_nothing(tmp_path, capsys, argv, said):
    """Checked before anything is written: the design against the schema, the stages, the glass."""
    if argv[0] == "--design":
        typo = tmp_path / "typo.toml"
        typo.write_text((ROOT / "scenes" / "ini_wearable.toml").read_text().replace("\nname = ", "\nnmae = ", 1))
        argv = ["--design", str(typo)]
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        rv.main(["--out", str(out), *argv])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.count("\n") == 1 and said in err and "Traceback" not in err, err
    assert not out.exists()
