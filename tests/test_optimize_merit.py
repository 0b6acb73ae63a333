"""The light-field merit: Jacobian against finite differences, and a short optimization.

Small samplings (4 corner lenslets × 3 CDP depths × 3×3 fields × 9 pupil rays) keep
these tests quick; the merit's code path is the one `lfsim optimize` runs.
"""

import copy
import json

import numpy as np
import pytest

import lfsim
from lfsim.cli import main
from lfsim.design.design import Design
from lfsim.optimize.merit import IniMerit

XY = ("x2y0", "x0y2", "x0y3")


def _design(scenes, tmp_path, variables, **extra):
    d0 = lfsim.load(scenes / "ini_freeform.toml")
    raw = copy.deepcopy(d0.raw)
    raw["optimize"] = {"variables": variables, "sampling": {"stride": [16, 8], "fields": 3, "pupil": 2},
                       "weights": {"distortion": 0.1}, **extra}
    return Design.from_dict(raw, str(tmp_path / "ff.toml"))


@pytest.fixture(scope="module")
def freeform_merit(tmp_path_factory):
    from pathlib import Path

    scenes = Path(__file__).resolve().parents[1] / "scenes"
    d = _design(scenes, tmp_path_factory.mktemp("m"),
                ["S3.x2y0", "S4.x2y1", "S1.curvature", "A1a.curvature", "object.distance", "tunable"],
                targets={"spot_axis_max_arcmin": 0.5, "gd_mean_deg": 0.3, "min_prism_thickness": 25.0,
                         "aperture_margin_mm": 1.0, "fov_deg": [30.0, 18.0],
                         "pixel_arcmin": [3.0, 3.0], "display_mismatch_max": 0.0,
                         "footprint_max_mm": 1.6})
    return IniMerit(d, d.optimize)


def _dense(M, x):
    return M.evaluate(x, derivatives=False, dense=True)[0]


def _central(M, x0, j: int, h: float, rows) -> np.ndarray:
    """Central difference of the dense residuals ``rows`` in column j, step h."""
    xp, xm = x0.copy(), x0.copy()
    xp[j] += h
    xm[j] -= h
    return (_dense(M, xp)[rows] - _dense(M, xm)[rows]) / (2 * h)


def test_merit_jacobian_matches_central_differences(freeform_merit):
    """Every residual block (spot, spot per axis, GD, PA, distortion, crosstalk, TIR,
    apertures, EFL, FOV, pixel, display, footprint, thickness) against
    central differences of the exact residuals: rays re-aimed, display layout and
    paraxial references moving with the design."""
    M = freeform_merit
    x0 = M.x0
    r, J, det = M.evaluate(x0, dense=True)  # every row, so that rows line up between points
    assert np.isfinite(r).all() and np.isfinite(J).all() and det["rays_lost"] == 0
    assert det["spot_axis_max"] > 0 and det["gd_max"] > 0 and det["gd_mean"] > 0  # the hinge blocks are active
    assert det["prism_thickness"] > 0 and det["fov"] > 0 and det["pixel"] > 0 and det["display"] > 0
    assert det["footprint"] > 0 and min(det["footprint_mm"]) > 1.6
    assert sum(v for k, v in det.items() if k.startswith("aperture_")) > 0  # rays within the margin
    for j in range(len(x0)):
        h = 1e-6 * max(1.0, abs(x0[j])) if M.cols[j].state is None else 1e-4
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        rp, rm = _dense(M, xp), _dense(M, xm)
        fd = (rp - rm) / (2 * h)
        # a hinge row that switches on or off between x − h and x + h has no central difference
        kink = (rp == 0.0) != (rm == 0.0)
        second = None
        a = 0
        for name, n in M.layout:
            blk = slice(a, a + n)
            a += n
            keep = ~kink[blk]
            scale = np.abs(fd[blk][keep]).max(initial=0.0)
            if scale == 0.0:
                assert np.abs(J[blk, j][keep]).max(initial=0.0) == 0.0, (M.cols[j].label, name)
                continue
            err = np.abs(fd[blk] - J[blk, j])[keep].max()
            # Bound: 2e-6 of the block's largest derivative (+ 1e-8) or 4x the difference's own
            # noise, whichever is larger; at most 2e-5 of it (+ 1e-7), which a wrong derivative
            # must exceed. Noise: the same difference at 2h moves by 3x its truncation (∝ h²) plus
            # its rounding (∝ 1/h); measured only where the error passes the floor (one column
            # here, 0.12 of the ceiling), the only place the larger of the two can matter.
            floor, noise = 2e-6 * scale + 1e-8, 0.0
            if err > floor:
                if second is None:
                    xp2, xm2 = x0.copy(), x0.copy()
                    xp2[j] += 2 * h
                    xm2[j] -= 2 * h
                    second = (_dense(M, xp2), _dense(M, xm2))
                rp2, rm2 = second
                smooth = ~(kink | ((rp2 == 0.0) != (rm2 == 0.0)))[blk]
                noise = np.abs((rp2 - rm2)[blk] / (4 * h) - fd[blk])[smooth].max(initial=0.0)
            tol = max(floor, 4 * noise)
            assert tol <= 2e-5 * scale + 1e-7, (M.cols[j].label, name, noise, scale)
            assert err <= tol, (M.cols[j].label, name, err, scale, noise)
        assert kink.sum() <= 2, (M.cols[j].label, kink.sum())


def test_lean_jacobian_equals_the_dense_one(freeform_merit, monkeypatch):
    """The lean evaluation (sub-systems in chunks, the re-aiming and the display
    layout's chain rule inside the kernel, inactive hinge rows dropped) gives the
    dense evaluation's merit, JᵀJ, Jᵀr and block sums to 1e-12 (relative to the
    largest entry), at a point where hinges are active and inactive."""
    from lfsim.optimize import merit as merit_mod

    M = freeform_merit
    x = M.x0 * (1.0 + 1e-3)
    rd, Jd, detd = M.evaluate(x, dense=True)
    monkeypatch.setattr(merit_mod, "MERIT_RAY_COPIES", 3000)  # several chunks
    r, J, det = M.evaluate(x)
    assert r.size < 0.5 * rd.size  # rows were dropped
    S = len(M.figures["subs"])
    assert 3000 // ((len(M.cols) + 2) * 9 * len(M.rho)) < S  # and the sub-systems came in chunks
    assert abs(r @ r - rd @ rd) <= 1e-12 * (rd @ rd)
    for a, b in ((J.T @ J, Jd.T @ Jd), (J.T @ r, Jd.T @ rd)):
        assert np.max(np.abs(a - b)) <= 1e-12 * np.max(np.abs(b))
    for name, v in detd.items():
        if isinstance(v, float):
            assert det[name] == pytest.approx(v, rel=1e-12, abs=1e-300), name
    assert sum(v for k, v in det.items() if k in ("gd_max", "spot_axis_max", "crosstalk")) > 0
    rr = M.residuals(x)  # the residuals alone (rows with r = 0 dropped): the same merit
    assert rr.size <= r.size and abs(rr @ rr - r @ r) <= 1e-12 * (r @ r)


def test_residuals_are_deterministic(freeform_merit):
    x = freeform_merit.x0 * 1.001
    a = freeform_merit.residuals(x)
    b = freeform_merit.residuals(x)
    assert np.array_equal(a, b)


def test_optimize_cli_resume_and_bounds(scenes, tmp_path, capsys):
    """A short LM run lowers the merit and keeps every variable in its bounds; an
    interrupted run resumed from its checkpoint ends bit for bit where an
    uninterrupted run does, a later stage whose checkpoint went stale (its start
    moved when the earlier stage resumed to more iterations) included."""
    import tomllib

    variables = [{"name": "S3.x2y0", "min": -0.75, "max": -0.70}, "S3.x0y2", "S4.x2y1", "tunable"]
    d = _design(scenes, tmp_path, variables, stages=["relay_eyepiece", "integrated"], iterations=3)
    path = tmp_path / "ff.toml"
    import tomli_w

    path.write_text(tomli_w.dumps(d.raw))
    full, part = tmp_path / "full", tmp_path / "part"
    assert main(["optimize", str(path), "--out", str(full), "--no-analyze", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    st = doc["stages"][0]
    assert st["merit_end"] < 0.9 * st["merit_start"]
    assert -0.75 <= st["x_end"][0] <= -0.70
    opt = tomllib.loads((full / doc["optimized_design"]).read_text())
    s3 = next(s for s in opt["surfaces"] if s["name"] == "S3")
    assert s3["xy"]["x2y0"] == doc["stages"][-1]["x_end"][0]
    assert (full / "merit_history.png").stat().st_size > 0
    # Interrupted after 1 iteration, then resumed to 3.
    assert main(["optimize", str(path), "--out", str(part), "--no-analyze", "--iterations", "1", "--json"]) == 0
    capsys.readouterr()
    assert main(["optimize", str(path), "--out", str(part), "--no-analyze", "--resume", "--json"]) == 0
    doc2 = json.loads(capsys.readouterr().out)
    for a, b in zip(doc2["stages"], doc["stages"], strict=True):
        assert a["x_end"] == b["x_end"]
        assert [h["cost"] for h in a["history"]] == [h["cost"] for h in b["history"]]
    # The first stage's start is the design itself: a changed input is still refused.
    ck = part / "checkpoints" / "integrated.npz"
    assert ck.exists()
    moved = tmp_path / "moved.toml"
    s3 = next(s for s in d.raw["surfaces"] if s["name"] == "S3")
    s3["xy"]["x0y2"] = s3["xy"]["x0y2"] * 1.01
    moved.write_text(tomli_w.dumps(d.raw))
    assert main(["optimize", str(moved), "--out", str(part), "--no-analyze", "--resume"]) == 2
    assert "refusing to resume" in capsys.readouterr().err


def test_optimize_bad_input(scenes, tmp_path, capsys):
    assert main(["optimize", str(scenes / "ini_coaxial.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "optimize.variables" in err and "\n" not in err
    assert not (tmp_path / "o").exists()


def test_grid_weights_estimate_the_mean_over_every_lenslet(freeform_merit):
    """Each sampled lenslet stands for its nearest lenslets: the weights sum to the
    array's lenslet count per depth, and a field that is linear across the array
    has the same weighted mean over the sample as over all lenslets."""
    from lfsim.ini.subsystems import sample

    M = freeform_merit
    model = M.model0
    arr = model.arr
    for stride in ((4, 2), (5, 3), (16, 8), (1, 1)):
        subs = sample(model, stride=stride, symmetry="none")
        w = M._grid_weights(model, subs)
        per_depth = w.sum() / len(model.depths)
        assert per_depth == pytest.approx(arr.m * arr.n, rel=1e-12)
        if stride == (1, 1):
            assert np.all(w == 1.0)
        f = 0.3 * subs.m + 0.7 * subs.n  # exact for a linear field when both ends are sampled
        full = 0.3 * (arr.m - 1) / 2 + 0.7 * (arr.n - 1) / 2
        assert (w @ f) / w.sum() == pytest.approx(full, rel=1e-12), stride


def test_optimize_api_writes_the_before_after_analysis(scenes, tmp_path, capsys):
    """optimize.workflow.optimize() writes what `lfsim optimize` writes, the before/after
    analysis included; a bad --analyze-stride is refused before any work or output."""
    from lfsim.optimize.workflow import optimize

    d = _design(scenes, tmp_path, ["S3.x2y0"], stages=["integrated"], iterations=1)
    out = tmp_path / "o"
    doc = optimize(d, out, log=lambda m: None, analyze_stride=(16, 8))
    assert doc["before_after_stride"] == [16, 8] and "before_after.png" in doc["plots"]
    assert json.loads((out / "history.json").read_text())["before_after"] == json.loads(
        json.dumps(doc["before_after"]))
    for side in ("before", "after"):
        assert json.loads((out / side / "metrics.json").read_text())["summary"]["subsystems_evaluated"] > 0
    assert main(["optimize", str(scenes / "ini_freeform.toml"), "--out", str(tmp_path / "bad"),
                 "--analyze-stride", "0,0"]) == 2
    assert "--analyze-stride" in capsys.readouterr().err and not (tmp_path / "bad").exists()


@pytest.mark.parametrize("scene", ["ini_freeform.toml", "ini_coaxial.toml"])
def test_merit_figures_equal_the_analysis(scenes, tmp_path, scene):
    """The optimizer minimizes the numbers `lfsim analyze` reports: on the same sub-systems,
    fields and pupil rule, the merit's GD (Eq. 11), PA (Eq. 12) and RMS spot equal the
    analysis's to 1e-9 (both come from lfsim.metrics)."""
    from lfsim.analysis.ini_analysis import evaluate
    from lfsim.ini.model import IniModel
    from lfsim.metrics.spot import ARCMIN

    d0 = lfsim.load(scenes / scene)
    raw = copy.deepcopy(d0.raw)
    raw["optimize"] = {"variables": [next(n for n in d0.parameter_names() if n.endswith(".curvature"))]}
    d = Design.from_dict(raw, str(tmp_path / scene))
    n = d.ini.pupil
    M = IniMerit(d, d.optimize, stride=(8, 4), fields=3, pupil_nodes=2 * n)  # analyze's "gl2" rule
    M.evaluate(M.x0, derivatives=False)
    fig = M.figures
    res = evaluate(IniModel(d), subs=fig["subs"], refine=0)
    gd = np.where(res["chief_ok"][:, 0], res["gd"], np.nan)
    pa = np.where(res["pa_ok"], res["pa"], np.nan)
    rms = res["rms"] * ARCMIN
    for name, a, b in (("GD", fig["gd_deg"], gd), ("PA", fig["pa"], pa), ("RMS", fig["rms_spot_arcmin"], rms)):
        keep = np.isfinite(a) & np.isfinite(b)
        assert keep.mean() > 0.9, name
        np.testing.assert_allclose(a[keep], b[keep], rtol=0, atol=1e-9, err_msg=name)


def test_schedule_runs_in_one_call_honours_each_stage_and_resumes_bit_identically(scenes, tmp_path):
    """A [[optimize.stages]] schedule: each stage moves its own variables within its
    own bounds, with its own weights and sampling; an uninterrupted run and one killed
    in the middle of its second stage and resumed end on the same bits."""
    from lfsim.optimize.workflow import optimize

    b_lo, b_hi = -2.3, -2.25
    stages = [{"name": "a", "variables": [{"name": "S3.x2y0", "min": -0.75, "max": -0.70}, "tunable"],
               "iterations": 2},
              {"name": "b", "variables": ["S3.x2y0", {"name": "S4.x2y1", "min": b_lo, "max": b_hi}, "tunable"],
               "iterations": 3, "weights": {"gd": 8.0}, "stride": [8, 8]}]
    d = _design(scenes, tmp_path, ["S3.x2y0", "tunable"], stages=stages)
    assert d.optimize.schedule is not None
    s4 = next(s for s in d.raw["surfaces"] if s["name"] == "S4")
    assert not b_lo <= s4["xy"]["x2y1"] <= b_hi  # stage b has to move it into its box
    lines = []
    doc = optimize(d, tmp_path / "full", log=lines.append, analyze_stride=None)
    assert [r["stage"] for r in doc["stages"]] == ["a", "b"]
    a, b = doc["stages"]
    assert a["variables"][0] == "S3.x2y0" and len(a["variables"]) == 4 and len(b["variables"]) == 5
    assert -0.75 <= a["x_end"][0] <= -0.70 and -0.75 <= b["x_start"][0] <= -0.70
    assert b_lo <= b["x_end"][1] <= b_hi and b["stride"] == [8, 8] and a["stride"] == [16, 8]
    assert b["x_start"][0] == a["x_end"][0]  # stage b starts where stage a ended
    assert b["merit_end"] < b["merit_start"]
    # one line per iteration with the merit, the block shares, the damping, the step and an ETA
    it_lines = [ln for ln in lines if ln.lstrip().startswith(("a ", "b "))]
    assert len(it_lines) == a["iterations"] + b["iterations"]
    assert all("merit" in ln and "%" in ln and "lambda" in ln and "step" in ln and "ETA" in ln for ln in it_lines)
    header = (tmp_path / "full" / doc["optimized_design"]).read_text().splitlines()[:3]
    assert any("lfsim optimize" in ln and "--out" in ln for ln in header)

    class Killed(Exception):
        pass

    def kill_in_b(msg):
        if msg.lstrip().startswith("b 2/"):
            raise Killed

    with pytest.raises(Killed):
        optimize(d, tmp_path / "part", log=kill_in_b, analyze_stride=None)
    doc2 = optimize(d, tmp_path / "part", log=lambda m: None, analyze_stride=None, resume=True)
    for r1, r2 in zip(doc["stages"], doc2["stages"], strict=True):
        assert r1["x_end"] == r2["x_end"]
        assert [h["cost"] for h in r1["history"]] == [h["cost"] for h in r2["history"]]


def test_trial_points_skip_the_design_file_but_not_its_numbers(freeform_merit):
    """A trial point's model is built from the packed parameters (no design table
    written or validated); its merit equals that of the design written at x and
    re-read, to rounding (the file stores radii, 1/c)."""
    from lfsim.ini.model import IniModel

    M = freeform_merit
    x = M.x0 * (1.0 + 2e-3)
    fast = M._build_model(x)
    slow = IniModel(M.design_at(x))
    assert np.max(np.abs(fast.values0 - slow.values0)) <= 1e-12 * np.max(np.abs(slow.values0))
    assert np.allclose(fast.tl_power, slow.tl_power, rtol=1e-12, atol=0)
    r_fast = M.residuals(x)
    M._model = (x.tobytes(), slow)
    r_slow = M.residuals(x)
    assert r_fast.size == r_slow.size
    assert abs(r_fast @ r_fast - r_slow @ r_slow) <= 1e-9 * (r_slow @ r_slow)


def test_package_block_jacobian_matches_central_differences(scenes, tmp_path):
    """The package block (track, boxes, eye relief, clear diameter, tunable footprint) with
    every limit exceeded, against central differences of its exact residuals; its rows
    are the excess of lfsim.ini.package's figures over the limits, in µm."""
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    d0 = lfsim.load(scenes / "ini_freeform.toml")
    fig = package(IniModel(d0))
    box, pbox = fig["bounding_box_mm"], fig["prism_box_mm"]
    targets = {"track_max_mm": fig["track_mm"] - 2.0, "eye_relief_min_mm": fig["eye_relief_mm"] + 1.0,
               "box_max_mm": [v - 1.0 for v in box], "prism_box_max_mm": [v - 1.0 for v in pbox],
               "clear_diameter_max_mm": fig["max_clear_diameter_mm"] - 1.0,
               "tunable_aperture_mm": fig["tunable_footprint_mm"] - 1.0}
    d = _design(scenes, tmp_path, ["S4.position_z", "S4.tilt_x", "A1a.curvature", "A2b.thickness", "S3.x2y0"],
                targets=targets)
    M = IniMerit(d, d.optimize)
    x0 = M.x0
    r, J, det = M.evaluate(x0, dense=True)
    names = [n for n, _ in M.layout]
    a = sum(n for name, n in M.layout[:names.index("package")])
    blk = slice(a, a + dict(M.layout)["package"])
    res = r[blk] / 1000.0
    assert res.size == 10
    # excesses as lfsim.ini.package measures them (mm)
    np.testing.assert_allclose(res[[0, 7]], [2.0, 1.0], atol=1e-9)
    np.testing.assert_allclose(res[1:7], 1.0, atol=1e-9)
    np.testing.assert_allclose(res[8:10], 1.0, atol=1e-9)
    moved = 0
    for j in range(len(x0)):
        fd = _central(M, x0, j, 1e-5 * max(1.0, abs(x0[j])), blk)
        scale = np.abs(fd).max()
        if M.cols[j].name == "S3.x2y0":  # not a geometric column: left out of the block's derivatives
            assert np.all(J[blk, j] == 0.0)
            continue
        moved += scale > 0
        np.testing.assert_allclose(J[blk, j], fd, rtol=0, atol=1e-3 * scale + 1e-6, err_msg=M.cols[j].label)
    assert moved >= 3


def test_colour_block_jacobian_and_figure(scenes, tmp_path):
    """Lateral colour in the merit (weight ``colour``): its rows against central differences
    of the exact residuals (both wavelengths re-aimed, the display layout moving), its figure
    against `analyze`'s angle on the same sub-systems (the tangent difference is at least the
    angle and within 1/cos² of the field), its hinge, and no rows at the default weight 0."""
    from lfsim.analysis.ini_analysis import lateral_colour

    variables = ["S1.curvature", "A1a.curvature", "object.distance", "tunable"]
    off = IniMerit(_design(scenes, tmp_path, variables), _design(scenes, tmp_path, variables).optimize)
    off.evaluate(off.x0, derivatives=False)
    assert "colour" not in dict(off.layout)
    d = _design(scenes, tmp_path, variables, weights={"distortion": 0.1, "colour": 1.0},
                targets={"lateral_colour_max_arcmin": 2.0})
    M = IniMerit(d, d.optimize)
    x0 = M.x0
    r, J, det = M.evaluate(x0, dense=True)
    assert det["colour"] > 0 and det["colour_max"] > 0
    lay = dict(M.layout)
    names = [n for n, _ in M.layout]
    a = sum(n for name, n in M.layout[:names.index("colour")])
    blk = slice(a, a + lay["colour"] + lay["colour_max"])
    figure = M.evaluate(x0, derivatives=False)[2]
    lc = lateral_colour(M.model_at(x0), M.figures["subs"])
    ok = lc["ok"]
    assert figure["lateral_colour_max_arcmin"] >= np.max(lc["arcmin"][ok]) * (1 - 1e-9)
    assert figure["lateral_colour_max_arcmin"] <= np.max(lc["arcmin"][ok]) * 1.1
    for j in range(len(x0)):
        h = 1e-6 * max(1.0, abs(x0[j])) if M.cols[j].state is None else 1e-4
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        rp, rm = _dense(M, xp)[blk], _dense(M, xm)[blk]
        fd = (rp - rm) / (2 * h)
        keep = (rp == 0.0) == (rm == 0.0)  # hinge rows that do not switch
        scale = np.abs(fd[keep]).max()
        assert scale > 0, M.cols[j].label
        err = np.abs(fd - J[blk, j])[keep].max()
        assert err <= 2e-5 * scale + 1e-7, (M.cols[j].label, err, scale)


def test_edge_thickness_block_jacobian_with_decentred_and_tilted_lenses(scenes, tmp_path):
    """A relay lens whose decenter and tilt are variables (A1's faces, with its bending; the limit
    1 mm above its edge) gives a row per rim point (the least over the rim has a kink where
    the thinnest point moves), its rows the rim's shortfall in µm; every row against central
    differences of the exact residuals, off the axis and at the coaxial start."""
    from lfsim.optics.solids import EDGE_RIM_POINTS, edge_thickness, glass_pairs, rim_thickness

    variables = ["A1a.decenter_y", "A1b.decenter_y", "A1b.tilt_x", "A1a.curvature"]
    d0 = _design(scenes, tmp_path, variables)
    M0 = IniMerit(d0, d0.optimize)
    m = M0.model_at(M0.x0)
    pairs = glass_pairs(m.system, m.tracer.names, m.values0, m.spec.viewing_window)
    q = [m.system.surfaces[i].name for i, _, _ in pairs].index("A1a")
    i, j, rad = pairs[q]
    e0 = edge_thickness(m.tracer, m.values0, i, j, rad)
    d = _design(scenes, tmp_path, variables, targets={"min_edge_thickness": e0 + 1.0})
    M = IniMerit(d, d.optimize)
    w = 1000.0 * d.optimize.weights.thickness
    for off_axis in (True, False):
        x0 = M.x0.copy()
        if off_axis:
            x0[:3] = [0.4, -0.3, 1.5]  # a decentred, wedged element
        r, J, _ = M.evaluate(x0, dense=True)
        lay = [n for n, _ in M.layout]
        a = sum(n for _, n in M.layout[:lay.index("edge_thickness")])
        blk = slice(a, a + dict(M.layout)["edge_thickness"])
        assert dict(M.layout)["edge_thickness"] == len(pairs) - 1 + EDGE_RIM_POINTS
        rim = rim_thickness(m.tracer, M.model_at(x0).values0, i, j, rad)[0]
        np.testing.assert_allclose(r[blk][q:q + EDGE_RIM_POINTS], np.maximum(e0 + 1.0 - rim, 0.0) * w, rtol=1e-12)
        if not off_axis:  # coaxial: every rim point as thin as the coaxial formula
            np.testing.assert_allclose(rim, e0, rtol=0, atol=1e-12)
        for k in range(len(x0)):
            fd = _central(M, x0, k, 1e-6 * max(1.0, abs(x0[k])), blk)
            assert np.abs(fd).max() > 0, M.cols[k].label
            np.testing.assert_allclose(J[blk, k], fd, rtol=0, atol=1e-4 * np.abs(fd).max(), err_msg=M.cols[k].label)


def test_colour_block_holds_the_tunable_lens_of_a_start_without_listed_powers(scenes, tmp_path):
    """The wearable start lists no tunable powers: at 486 nm its 3 D state would need 7.82 D,
    outside the lens's 8.3-20 D. The colour block holds the primary's powers (as `analyze`'s
    lateral colour does) instead of solving them again, so a colour stage can run from the start."""
    d0 = lfsim.load(scenes / "ini_wearable.toml")
    assert "power_diopters" not in d0.raw["ini"]["tunable"]
    raw = copy.deepcopy(d0.raw)
    del raw["optimize"]["stages"]
    raw["optimize"]["weights"]["colour"] = 100.0
    raw["optimize"]["sampling"] = {"stride": [16, 8], "fields": 3, "pupil": 2}
    d = Design.from_dict(raw, str(tmp_path / "w.toml"))
    M = IniMerit(d, d.optimize)
    for m in M._colour0:
        assert m.tl_power == M.model0.tl_power
    r = M.residuals(M.x0)
    assert np.isfinite(r).all() and dict(M.layout)["colour"] > 0


def test_a_refused_optimization_writes_nothing(scenes, tmp_path, capsys):
    """A stage whose merit cannot be built (a colour weight on a one-wavelength design) is
    refused in one line, exit 2, before the output folder or its checkpoints exist."""
    import tomli_w

    raw = copy.deepcopy(lfsim.load(scenes / "ini_freeform.toml").raw)
    raw["system"]["wavelengths_nm"] = [587.5618]
    raw["system"]["primary_wavelength_nm"] = 587.5618
    raw["optimize"] = {"variables": ["S3.x2y0"], "weights": {"colour": 1.0}, "iterations": 1}
    p = tmp_path / "mono.toml"
    p.write_text(tomli_w.dumps(raw))
    out = tmp_path / "out"
    assert main(["optimize", str(p), "--out", str(out), "--no-analyze"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "optimize.weights.colour" in err, err
    assert not out.exists()


def test_hinge_model_rows_equal_the_penalty_rows_with_a_jacobian_everywhere(scenes, tmp_path):
    """lm-hinge's form of the mechanical constraints (package, glass edge and centre, prism
    thickness): the same merit and block sums as the penalty form, every row kept with
    its signed excess g (negative while the limit holds) as the last len(g) residuals'
    max(0, g), and G against central differences of g for every variable, the display
    gap and an XY term included (the penalty form's package derivatives leave both out)."""
    from lfsim.ini.model import IniModel
    from lfsim.ini.package import package

    d0 = lfsim.load(scenes / "ini_freeform.toml")
    fig = package(IniModel(d0))
    box, pbox = fig["bounding_box_mm"], fig["prism_box_mm"]
    targets = {"track_max_mm": fig["track_mm"] - 2.0, "eye_relief_min_mm": fig["eye_relief_mm"] - 1.0,
               "box_max_mm": [v + 1.0 for v in box], "prism_box_max_mm": [pbox[0] - 1.0, pbox[1] + 1.0, pbox[2]],
               "clear_diameter_max_mm": fig["max_clear_diameter_mm"] + 1.0,
               "tunable_aperture_mm": fig["tunable_footprint_mm"] - 1.0, "min_prism_thickness": 25.0,
               "min_edge_thickness": 1.0}
    variables = ["S4.position_z", "S4.tilt_x", "A1a.curvature", "A2b.thickness", "S3.x2y0", "object.distance"]
    d = _design(scenes, tmp_path, variables, targets=targets)
    P, H = IniMerit(d, d.optimize), IniMerit(d, d.optimize, hinge_model=True)
    x0 = H.x0
    rp, Jp, dp = P.evaluate(x0, dense=True)
    rh, Jh, dh = H.evaluate(x0)
    g, G = H.hinges
    assert rp @ rp == pytest.approx(rh @ rh, rel=1e-12)
    for name in ("package", "thickness", "edge_thickness", "prism_thickness"):
        assert dp[name] == pytest.approx(dh[name], rel=1e-12, abs=1e-9), name
    assert np.array_equal(rh[-len(g):], np.maximum(g, 0.0))
    np.testing.assert_array_equal(Jh[-len(g):], np.where((g > 0)[:, None], G, 0.0))
    live = np.isfinite(g)
    assert (g[live] > 0).any() and (g[live] < 0).any()  # limits that hold and limits that do not
    assert np.all(G[~live] == 0.0)
    moved = set()
    for j, c in enumerate(H.cols):
        h = 1e-6 * max(1.0, abs(x0[j]))
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        H.evaluate(xp, derivatives=False)
        gp = H.hinges[0].copy()
        H.evaluate(xm, derivatives=False)
        with np.errstate(invalid="ignore"):  # -inf - -inf: a limit that is off
            fd = np.where(live, (gp - H.hinges[0]) / (2 * h), 0.0)
        scale = np.abs(fd).max()
        if scale > 0:
            moved.add(c.name)
        np.testing.assert_allclose(G[:, j], fd, rtol=0, atol=1e-4 * scale + 1e-6, err_msg=c.label)
    assert {"S3.x2y0", "object.distance", "S4.position_z"} <= moved


@pytest.mark.parametrize("edge, step, renders", [(None, 0, True), ("lo", 0, True), ("lo", -1, False),
                                                  ("hi", 0, True), ("hi", 1, False)])
def test_display_mismatch_is_the_renderers_rule(scenes, edge, step, renders):
    """``IniModel.display_mismatch`` (the ``display`` block's figure and the renderer's check)
    is over 1 exactly where the renderer refuses the design (its outer EIs would fall off the display, or the display
    would hold a whole EI for no lenslet): the shipped wearable's layout (p_EI about 1.06 mm at 1 D)
    against displays of 8 µm pixels whose EI width w lies just inside or just outside
    p_EI·(1 ± 1/M) on the binding axis (the closed form of M·|p_EI − w|/p_EI ≤ 1), and 125 px."""
    from lfsim.design import DesignError
    from lfsim.ini.model import IniModel
    from lfsim.render.display import check_display_size

    d = lfsim.load(scenes / "ini_wearable_optimized.toml")
    k = 1
    mo0 = IniModel(d)
    p0 = np.abs(mo0.state(k).p_ei)
    count = np.array([mo0.arr.m, mo0.arr.n], dtype=np.float64)
    lo = int(np.max(np.ceil(p0 * (1 - 1 / count) / 0.008 - 1e-9)))
    hi = int(np.min(np.floor(p0 * (1 + 1 / count) / 0.008 + 1e-9)))
    assert lo <= 125 <= hi  # the shipped 125 px render (the ten-stage design's lie at the edge, lo = 125)
    ppe = 125 if edge is None else (lo if edge == "lo" else hi) + step
    d.ini.pixels_per_ei = (ppe, ppe)
    mo = IniModel(d)
    mis = mo.display_mismatch(np.array([mo.state(k).p_ei]))[0]
    want = np.array([mo.arr.m, mo.arr.n]) * np.abs(np.abs(mo.state(k).p_ei) - ppe * 0.008) / np.abs(mo.state(k).p_ei)
    assert mis == pytest.approx(want, rel=1e-14)
    if renders:
        check_display_size(mo, k, mo.state(k).p_ei)
        assert mis.max() <= 1.0
    else:
        with pytest.raises(DesignError, match="pixels_per_ei"):
            check_display_size(mo, k, mo.state(k).p_ei)
        assert mis.max() > 1.0


def test_a_tunable_lens_that_is_not_a_variable_is_held(scenes, tmp_path):
    """Variables without "tunable", on a design whose file solves the tunable powers for the
    CDP depths (no power_diopters): the merit holds the start's powers at every trial point
    (solved again per design, they would move under derivatives that hold them), so the
    Jacobian of the spot, GD and PA blocks matches central differences, and the design it
    writes carries those powers."""
    d = _design(scenes, tmp_path, ["A1a.curvature", "object.distance"],
                targets={"spot_axis_max_arcmin": 0.8, "gd_max_deg": 0.2, "pa_max": 0.05})
    assert d.ini.tunable_power_diopters is None  # solved when the file loads
    M = IniMerit(d, d.optimize)
    x0 = M.x0
    r, J, _ = M.evaluate(x0, dense=True)
    p0 = [1000.0 * p for p in M.model0.tl_power]
    for j in range(len(x0)):
        h = 1e-6 * max(1.0, abs(x0[j]))
        xp, xm = x0.copy(), x0.copy()
        xp[j] += h
        xm[j] -= h
        assert [1000.0 * p for p in M.model_at(xp).tl_power] == pytest.approx(p0, abs=1e-12)
        fd = (_dense(M, xp) - _dense(M, xm)) / (2 * h)
        a = 0
        for name, n in M.layout:
            blk = slice(a, a + n)
            a += n
            if name in ("spot", "spot_axis_max", "gd", "gd_max", "pa", "pa_hinge"):
                scale = np.abs(fd[blk]).max(initial=0.0)
                assert np.abs(fd[blk] - J[blk, j]).max(initial=0.0) <= 2e-5 * scale + 1e-7, (M.cols[j].label, name)
    x1 = x0 * (1.0 + 1e-3)
    assert M.design_at(x1).ini.tunable_power_diopters == pytest.approx(p0, abs=1e-12)


def test_footprint_block_is_eq5_of_each_state(freeform_merit):
    """The ``footprint`` block's figure per CDP state is ``lfsim ini``'s d_v of Eq. (5) (the mean
    of its x and y widths, the reference PA divides by); the hinge reads (d_v − limit)/limit in %
    times its weight."""
    from lfsim.ini.model import IniModel

    M = freeform_merit
    r, _, det = M.evaluate(M.x0, derivatives=False, dense=True)
    mo = IniModel(M.design_at(M.x0))
    want = [float(np.mean(mo.state(k).d_v)) for k in range(len(mo.depths))]
    assert det["footprint_mm"] == pytest.approx(want, rel=1e-12)
    a = 0
    for name, n in M.layout:
        if name == "footprint":
            rows = r[a:a + n]
        a += n
    w, lim = M.spec.weights.footprint, M.spec.targets.footprint_max_mm
    assert rows == pytest.approx([(v - lim) / lim * 100.0 * w for v in want], rel=1e-12)
    assert det["footprint"] == pytest.approx(float(rows @ rows), rel=1e-12)
