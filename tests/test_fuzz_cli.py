"""Fuzzing of every ``lfsim`` verb with generated arguments and generated or corrupted files.

Each case builds a command line for one verb from that verb's options, each
given a value drawn from a pool of good values (small, so that a valid run is
quick) and bad ones (zero, negative, NaN, inf, huge, empty, malformed pairs,
missing or corrupted files, a folder where a file belongs). The contract of
the command: every case ends with exit status 0, 1 or 2 and no traceback (an
exception escaping ``main`` fails the test), an error is one line on standard
error, and a run refused or failed (exit 2) leaves every pre-existing output
(a previous output folder, an output file, a baseline) byte for byte as it
was. Exit 1 is a finished run whose check failed (``compare``,
``gradcheck``, ``regress``): it writes its report like a passing one.

Example counts: ``DEFAULT_CASES`` (a few hundred) in the normal run;
``LFSIM_FUZZ_EXAMPLES=N`` runs N; ``-m slow`` runs 1000.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from lfsim.cli import main

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
DEFAULT_CASES = 240
_N = os.environ.get("LFSIM_FUZZ_EXAMPLES")

TINY_INI = """
name = "tiny InI"
[system]
wavelengths_nm = [587.5618]
[object]
distance = 4.5
material = "air"
[arrays.mla]
m = 3
n = 3
pitch = [1.0, 1.0]
[[surfaces]]
name = "MLA"
type = "paraxial"
focal_length = 3.5
array = "mla"
aperture = { type = "rectangular", half_width = [0.5, 0.5] }
thickness = 46.75
[[surfaces]]
name = "TL"
type = "paraxial"
focal_length = inf
thickness = 0.0
[[surfaces]]
name = "EP"
type = "paraxial"
focal_length = 31.0
thickness = 31.0
[[surfaces]]
name = "VW"
radius = inf
dummy = true
[ini]
mla = "mla"
pixel_pitch = 0.04
pixels_per_ei = [25, 25]
cdp_diopters = [1.0]
viewing_window = "VW"
[ini.tunable]
surface = "TL"
range_diopters = [-10.0, 10.0]
[ini.eye]
model = "ideal"
pupil_diameter = 4.0
[ini.analysis]
fields = 3
pupil = 4
mtf_grid = 16
refine = 0
[tolerance]
trials = 2
seed = 1
batch = 1
[tolerance.sampling]
stride = [1, 1]
fields = 3
pupil = 4
mtf_grid = 16
refine = 0
[tolerance.targets]
gd_max_deg = 1.0
[[tolerance.parameters]]
name = "gap"
key = "object.distance"
limit = 0.01
distribution = "truncated_normal"
sigma = 0.005
"""

CONTENT = """
name = "fuzz wall"
[view]
design = "@DESIGN@"
cdp_mm = 1000.0
focus_mm = [1000.0]
pupil_diameter = 3.0
[[objects]]
name = "wall"
type = "quad"
corners = [[-300.0, -200.0, -1000.0], [300.0, -200.0, -1000.0], [-300.0, 200.0, -1000.0]]
texture = { type = "noise", feature_mm = 20.0, texel_mm = 5.0, seed = 3 }
radiance = 1.0
"""


def _write_images(d: Path) -> None:
    from lfsim.render.focal_stack import write_exr, write_png

    rng = np.random.default_rng(0)
    a = rng.random((9, 16, 3), dtype=np.float32)
    write_exr(d / "a.exr", a, {})
    write_exr(d / "b.exr", np.clip(a + 0.01, 0, 1), {})
    write_png(d / "a.png", a)
    write_exr(d / "small.exr", a[:4, :4], {})


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    """Good, corrupted and missing inputs, built once."""
    d = tmp_path_factory.mktemp("fuzz_files")
    (d / "tiny_ini.toml").write_text(TINY_INI)
    (d / "content.toml").write_text(CONTENT.replace("@DESIGN@", str(d / "tiny_ini.toml")))
    shutil.copy(SCENES / "cooke_triplet.toml", d / "lens.toml")
    shutil.copy(SCENES / "cooke_triplet_optimize.toml", d / "lens_opt.toml")
    (d / "rays.csv").write_text("x,y,z,dx,dy,dz\n0,0,-5,0,0,1\n0,2,-5,0,0.01,1\n")
    text = TINY_INI
    (d / "cut.toml").write_text(text[: len(text) // 2])                          # truncated
    (d / "garbage.toml").write_bytes(bytes(range(256)) * 4)                       # binary
    (d / "bad_value.toml").write_text(text.replace("focal_length = 3.5", "focal_length = nan"))
    (d / "no_ini.toml").write_text(text.split("[ini]")[0])
    (d / "bad_content.toml").write_text(CONTENT.replace("@DESIGN@", str(d / "tiny_ini.toml")).replace("radiance = 1.0",
                                                                                           "radiance = -1"))
    (d / "bad_rays.csv").write_text("x,y,z,dx,dy,dz\n0,0,nan,0,0,1\n")
    shutil.copy(ROOT / "tests" / "data" / "lensfiles" / "dar_test.seq", d / "lens.seq")
    shutil.copy(ROOT / "tests" / "data" / "lensfiles" / "US00583336-2-scaled.zmx", d / "lens.zmx")
    (d / "bad.seq").write_text("SO 0 1e11\nS 0 1 NOSUCHGLASS_XYZ\nS 0 abc\nSI 0 0\n")
    (d / "bad.zmx").write_bytes(b"\xff\xfe" + "MODE SEQ\nSURF 0\n  TYPE TOROIDAL\n".encode("utf-16-le"))
    (d / "corrupt.exr").write_bytes(b"v/1\x01" + os.urandom(200))
    (d / "empty").write_text("")
    (d / "a_folder").mkdir()
    _write_images(d)
    return {p.name: p for p in d.iterdir()}


def _snapshot(root: Path) -> dict[str, str]:
    """Every file under ``root`` (names relative to it) and a hash of its bytes."""
    if not root.exists():
        return {}
    if root.is_file():
        return {".": hashlib.sha256(root.read_bytes()).hexdigest()}
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


# --------------------------------------------------------------- value pools
BAD_NUM = ["0", "-1", "nan", "inf", "-inf", "1e308", "abc", ""]
BAD_PAIR = ["0,0", "-4,3", "4", "4,3,2", "a,b", "", "1e9,1e9", "3.5,2"]


def _pool(good: list[str], bad: list[str]):
    """Good values three times as likely as bad ones (most cases still end early on one bad option)."""
    return st.sampled_from(good * 3 + bad)


def _file(files, good: list[str], bad: tuple[str, ...] = ("cut.toml", "garbage.toml", "bad_value.toml",
                                                          "empty", "a_folder", "missing.toml")):
    names = list(good) * 4 + list(bad)
    return st.sampled_from(names).map(lambda n: str(files[n]) if n in files else str(Path(files["empty"]).parent / n))


SEEDS = _pool(["0", "1"], ["-1", "4294967296", "x"])
SET = st.sampled_from(["object.distance=4.6", "mla.pitch_x=1.0", "surfaces[2].thickness=31.0",
                       "object.distance=nan", "nonsense=1", "object.distance", "surfaces[99].thickness=1"])


def _options(draw, spec: dict) -> list[str]:
    """A subset of the verb's options with generated values; flags (value None) appear or not."""
    argv: list[str] = []
    for flag, strat in spec.items():
        if draw(st.booleans()):
            argv += [flag] if strat is None else [flag, draw(strat)]
    return argv


def verbs(files) -> dict:
    """Per verb: (positional-argument strategies, option strategies, output kind) — outputs: None, "file"
    (``--out FILE``), "dir" (``--out DIR``), "baseline" (regress)."""
    ini = _file(files, ["tiny_ini.toml"])
    lens = _file(files, ["lens.toml"])
    content = _file(files, ["content.toml"], ("bad_content.toml", "garbage.toml", "missing.toml", "a_folder"))
    res = _pool(["16,9", "12,7"], BAD_PAIR)
    spp = _pool(["1", "2"], BAD_NUM + ["100000000"])
    hours = _pool(["1"], ["0", "nan", "-1", "1e-9"])
    image = _file(files, ["a.exr", "a.png", "b.exr"], ("small.exr", "corrupt.exr", "empty", "missing.exr",
                                                       "garbage.toml"))
    return {
        "trace": ([lens], {"--rays": _file(files, ["rays.csv"], ("bad_rays.csv", "empty", "missing.csv")),
                           "--wavelength-nm": _pool(["550", "486.1327"], BAD_NUM),
                           "--precision": _pool(["float64", "float32"], ["float16"]), "--set": SET,
                           "--json": None}, "file"),
        "first-order": ([st.one_of(lens, ini)], {"--wavelength-nm": _pool(["587.56"], BAD_NUM),
                                                 "--method": _pool(["auto", "paraxial", "parabasal"], ["exact"]),
                                                 "--set": SET, "--json": None}, None),
        "params": ([st.one_of(lens, ini)], {"--set": SET, "--json": None}, None),
        "layout": ([lens], {"--set": SET, "--json": None}, "dir"),
        "ini": ([ini], {"--json": None, "--set": SET}, None),
        "import": ([_file(files, ["lens.seq", "lens.zmx"], ("bad.seq", "bad.zmx", "empty", "garbage.toml",
                                                           "a_folder", "missing.seq"))], {}, "toml"),
        "export": ([st.one_of(lens, ini)], {"--zmx": st.sampled_from(["ZMX", "ZMX", "BADEXT"]),
                                            "--seq": st.sampled_from(["SEQ", "SEQ", str(files["a_folder"])]),
                                            "--lenslet": _pool(["1,1"], ["x", "-1,0", "99,0", ""]),
                                            "--set": SET}, "lensfile"),
        "analyze": ([ini], {"--stride": _pool(["1,1", "2,2"], BAD_PAIR), "--symmetry": _pool(["none", "x"], ["z"]),
                            "--depths": _pool(["1"], ["2", "nan", "x"]), "--no-plots": None, "--json": None,
                            "--set": SET}, "dir"),
        "optimize": ([_file(files, ["lens_opt.toml"], ("lens.toml", "cut.toml", "missing.toml"))],
                     {"--iterations": _pool(["1", "2"], ["0", "-3", "x"]), "--solver": _pool(["lm"], ["newton"]),
                      "--no-analyze": None, "--json": None}, "dir"),
        "focal-stack": ([ini], {"--content": content, "--resolution": res, "--spp": spp, "--seed": SEEDS,
                                "--focus-mm": _pool(["800", "700,1200"], ["0", "-5", "nan", "x"]),
                                "--cdp-mm": _pool(["1000", "inf"], ["0", "nan", "x"]),
                                "--pupil-mm": _pool(["3"], ["0", "nan", "-2"]),
                                "--optics": _pool(["analytic"], ["lens"]), "--max-hours": hours,
                                "--max-memory-gb": _pool(["16"], ["0", "1e-6"]), "--set": SET, "--json": None},
                        "dir"),
        "gradcheck": ([ini], {"--param": _pool(["object.distance", "MLA.power"], ["nope", ""]), "--content": content,
                              "--resolution": res, "--spp": spp, "--seed": SEEDS,
                              "--rel-step": _pool(["1e-6"], BAD_NUM), "--fd-points": _pool(["1"], ["0", "-2"]),
                              "--max-hours": hours, "--json": None}, None),
        "compare": ([image, image], {"--min-psnr": _pool(["20", "60"], ["nan", "x"]),
                                     "--min-ssim": _pool(["0.5"], ["2", "nan"]),
                                     "--max-abs": _pool(["0.5"], ["-1", "nan"]), "--json": None}, "dir"),
        "regress": ([ini], {"--content": content, "--resolution": res, "--spp": spp, "--seed": SEEDS,
                            "--update": None, "--no-metrics": None, "--stride": _pool(["1,1"], BAD_PAIR),
                            "--junit": st.sampled_from(["JUNIT", str(files["a_folder"])]), "--max-hours": hours,
                            "--json": None}, "baseline"),
        "tolerance": ([ini], {"--trials": _pool(["1", "2"], ["0", "-1", "1000000000000"]),
                              "--seed": _pool(["0"], ["-1"]), "--batch": _pool(["1"], ["0"]),
                              "--scheduler": _pool(["serial"], ["tcp://127.0.0.1:1", "http://x"]),
                              "--no-sensitivity": None, "--no-plots": None, "--resume": None,
                              "--max-hours": hours, "--json": None}, "dir"),
        "sweep": ([ini], {"--set": _pool(["object.distance=4.4:4.6:2", "mla.pitch_x=1.0"],
                                         ["object.distance=1:2:0", "object.distance=1:2:100000000", "x=1:2:3",
                                          "object.distance=a:b:2"]),
                          "--stride": _pool(["1,1"], BAD_PAIR), "--scheduler": _pool(["serial"], ["tcp://127.0.0.1:1"]),
                          "--max-points": _pool(["10"], ["0", "-1"]), "--max-hours": hours, "--json": None},
                  "dir"),
    }


MANIFEST = {"layout": "summary.json", "analyze": "metrics.json", "optimize": None, "focal-stack": "index.json",
            "compare": "compare.json", "tolerance": None, "sweep": "sweep.json"}


@st.composite
def command(draw, files, out_root: Path):
    spec = verbs(files)
    verb = draw(st.sampled_from(sorted(spec)))
    positional, options, out_kind = spec[verb]
    argv = [verb] + [draw(p) for p in positional] + _options(draw, options)
    if verb in ("focal-stack", "gradcheck", "regress"):  # a valid render stays tiny
        for flag, value in (("--resolution", "16,9"), ("--spp", "1"), ("--content", str(files["content.toml"]))):
            if flag not in argv:
                argv += [flag, value]
    if verb == "sweep" and "--scheduler" not in argv:
        argv += ["--scheduler", "serial"]  # a local Dask cluster per case would make the run minutes long
    if verb == "tolerance" and "--scheduler" not in argv:
        argv += ["--scheduler", "serial"]
    if verb == "regress":
        argv += ["--baseline", str(out_root / "baseline"), "--out", str(out_root / "out")]
        argv = [str(out_root / "report.xml") if a == "JUNIT" else a for a in argv]
    elif out_kind == "toml":
        argv += ["--out", str(out_root / "out.toml")]
    elif out_kind == "lensfile":
        names = {"ZMX": "out.zmx", "SEQ": "out.seq", "BADEXT": "out.txt"}
        argv = [str(out_root / names[a]) if a in names else a for a in argv]
    elif out_kind == "file":
        if draw(st.booleans()):
            argv += ["--out", str(out_root / "out.csv")]
    elif out_kind == "dir":
        argv += ["--out", str(out_root / "out")]
    # what is there before the run: nothing, an earlier output of this verb, or a foreign file
    before = draw(st.sampled_from(["none", "previous", "foreign"]))
    return argv, verb, before


def _prepare(out_root: Path, verb: str, before: str) -> None:
    out = out_root / "out"
    if before == "none":
        return
    if verb == "trace":
        (out_root / "out.csv").write_text("earlier output\n")
        return
    if verb in ("import", "export"):
        for name in ("out.toml", "out.zmx", "out.seq"):
            (out_root / name).write_text("earlier output\n")
        return
    out.mkdir(parents=True, exist_ok=True)
    if before == "previous" and MANIFEST.get(verb):
        (out / MANIFEST[verb]).write_text('{"earlier": true}\n')
    (out / "notes.txt").write_text("a file the user keeps here\n")
    if verb == "regress":
        base = out_root / "baseline"
        base.mkdir(exist_ok=True)
        (base / "baseline.json").write_text('{"earlier": true}\n')


def _check(argv, rc, out_text, err, snapshot_before, out_root):
    cmd = " ".join(argv)
    assert rc in (0, 1, 2), f"{cmd}: exit status {rc!r}"
    assert "Traceback" not in err and "Traceback" not in out_text, f"{cmd}:\n{err}"
    if rc == 2:
        last = err.strip().splitlines()[-1] if err.strip() else ""
        assert last.startswith("lfsim: error: ") or last.startswith("usage:"), f"{cmd}: {err!r}"
    if rc == 2:  # exit 1 is a finished run whose check failed: its report is written, as on success
        assert _snapshot(out_root) == snapshot_before, f"{cmd}: exit {rc} changed the outputs there before"


def _settings(n: int) -> settings:
    return settings(max_examples=int(_N) if _N else n, deadline=None, derandomize=not _N, database=None,
                    suppress_health_check=list(HealthCheck))


@st.composite
def case_in(draw, files, root: Path):
    k = draw(st.integers(0, 10 ** 9))
    out_root = root / f"c{k}"
    if out_root.exists():
        shutil.rmtree(out_root)
    out_root.mkdir(parents=True)
    argv, verb, before = draw(command(files, out_root))
    return argv, verb, before, out_root


def _one(case, capsys):
    argv, verb, before, out_root = case
    _prepare(out_root, verb, before)
    snap = _snapshot(out_root)
    log = os.environ.get("LFSIM_FUZZ_LOG")  # a file: one line per case (exit status, seconds, command)
    if log:
        with open(log, "a") as f:
            f.write(f"start {' '.join(argv)}\n")
    t0 = time.perf_counter()
    try:
        rc = main(argv)
    except SystemExit as e:  # argparse: usage errors exit 2
        rc = e.code
    if log:
        with open(log, "a") as f:
            f.write(f"{rc} {time.perf_counter() - t0:.2f} s {' '.join(argv)}\n")
    cap = capsys.readouterr()
    event(f"{verb}: exit {rc}")
    _check(argv, rc, cap.out, cap.err, snap, out_root)
    shutil.rmtree(out_root, ignore_errors=True)


def test_fuzz_every_verb(files, tmp_path, capsys):
    @_settings(DEFAULT_CASES)
    @given(case=case_in(files, tmp_path))
    def run(case):
        _one(case, capsys)

    run()


@pytest.mark.slow
def test_fuzz_every_verb_thousand_cases(files, tmp_path, capsys):
    @settings(max_examples=1000, deadline=None, derandomize=False, database=None,
              suppress_health_check=list(HealthCheck))
    @given(case=case_in(files, tmp_path))
    def run(case):
        _one(case, capsys)

    run()
