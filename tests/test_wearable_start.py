"""examples/wearable_start.py: a prism design's prism scaled, and the relay target that keeps its
first order.

The target is checked against an independent y–ν trace of the bench design's own relay (at scale
1 the relay that keeps the bench's first order is the bench's relay), and the scaled prism's
first-order map (the tracer's linearization) against the scaling law ``D P D⁻¹``."""

import importlib.util
import math
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from lfsim.design import Design, load
from lfsim.optics.materials import lookup

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "scenes" / "ini_freeform_optimized.toml"
sys.path.insert(0, str(ROOT / "examples"))
for name in ("relay_petzval", "wearable_start"):
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ROOT / "examples" / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        sys.modules[name] = mod  # dataclasses look their module up
        spec.loader.exec_module(mod)
ws = sys.modules["wearable_start"]


@pytest.fixture(scope="module")
def bench():
    design = load(BENCH)
    return design, ws.prism_maps(design)


def _ynu_relay(raw: dict, phi: float, lam: float, z_s1: float):
    """The bench relay's y–ν matrices by hand, AA plane → S1's plane: (AA → tunable lens,
    tunable lens → S1 plane), with the tunable lens of power ``phi`` (mm⁻¹)."""
    S = raw["surfaces"]
    names = [s.get("name") for s in S]
    i0, i1 = names.index("AA"), names.index("S1")
    z = float(S[names.index("L1")]["thickness"]) + float(S[names.index("L2")]["thickness"])  # L1 at z = 0
    A, M = np.eye(2), np.eye(2)
    n = 1.0
    for i in range(i0, i1):
        s = S[i]
        if i > i0:
            if s.get("type") == "paraxial":
                A, M = M, np.eye(2)
                M = np.array([[1.0, 0.0], [-phi, 1.0]]) @ M
            else:
                c = s["curvature"] if "curvature" in s else 1.0 / s["radius"]
                n2 = float(lookup(s["material"]).index(lam)) if s.get("material", "air") != "air" else 1.0
                M = np.array([[1.0, 0.0], [-(n2 - n) * c, 1.0]]) @ M
                n = n2
        t = float(s["thickness"])
        M = np.array([[1.0, t / n], [0.0, 1.0]]) @ M
        z += t
    M = np.array([[1.0, z_s1 - z], [0.0, 1.0]]) @ M
    return A, M


def test_at_scale_one_the_target_is_the_designs_own_relay(bench):
    design, (M, P, z_back, z_s1, rest, phis, model) = bench
    k1 = 1
    M0, a0, b0, (tx, ty) = ws.relay_target(M, P, phis, 1.0, 0.0, k1)
    for k in range(len(phis)):
        A, B = _ynu_relay(design.raw, phis[k], model.lam, z_s1)
        R = B @ A
        if k == k1:
            np.testing.assert_allclose(tx, R, atol=1e-9)
            np.testing.assert_allclose(ty, R, atol=1e-9)
            np.testing.assert_allclose(M0, R, atol=1e-9)
    # the tunable lens's part: T(φ) − T(φ₁) = −(φ − φ₁)·b0·a0ᵀ, a0 the AA → lens first row,
    # b0 the lens → S1 second column
    A, B = _ynu_relay(design.raw, phis[k1], model.lam, z_s1)
    def cross(u, v):
        return (u[0] * v[1] - u[1] * v[0]) / (np.linalg.norm(u) * np.linalg.norm(v))

    assert abs(cross(a0, A[0])) < 1e-9 and abs(cross(b0, B[:, 1])) < 1e-9
    R0 = _ynu_relay(design.raw, phis[0], model.lam, z_s1)
    np.testing.assert_allclose(R0[1] @ R0[0] - B @ A, -(phis[0] - phis[k1]) * np.outer(b0, a0), atol=1e-9)
    # the track after S1's plane: the prism's unfolded path and the 17.56 mm eye relief
    assert 95.0 < rest < 100.0


def test_the_scaled_prism_obeys_the_scaling_law(bench):
    design, (M, P, z_back, z_s1, rest, phis, model) = bench
    s = 0.95
    raw = tomllib.loads(BENCH.read_text())
    names = [t.get("name") for t in raw["surfaces"]]
    for t in ws.scale_prism(raw, s, z_s1, z_s1):
        raw["surfaces"][names.index(t["name"])] = t
    # scaled about S1's plane on the axis: S1's vertex moves toward the axis by 1 − s
    s1 = raw["surfaces"][names.index("S1")]
    g0 = design.raw["surfaces"][names.index("S1")]["global_position"]
    assert math.isclose(s1["global_position"][1], s * g0[1], rel_tol=1e-12)
    assert math.isclose(s1["norm_radius"], s * 15.0, rel_tol=1e-12)
    _, P2, _, z2, rest2, _, _ = ws.prism_maps(Design.from_dict(raw, "scaled"))
    D = np.diag([s, s, 1.0, 1.0])
    np.testing.assert_allclose(P2, D @ P @ np.linalg.inv(D), atol=2e-9, rtol=1e-8)
    assert math.isclose(z2, z_s1, abs_tol=1e-9)
    assert rest2 == pytest.approx(s * rest, rel=2e-3)  # the unfolded path scales (the OAR's aim moves a little)


@pytest.mark.parametrize("args, words", [
    (["--scale", "5"], "--scale 5.0: between 0.1 and 2"),
    (["--scale", "0.7", "--glasses", "N-LAK22,N-LAK22"], "four glasses"),
    (["--scale", "0.7", "--glasses", "N-LAK22,N-LAK22,N-LAK22,XYZ"], "XYZ"),
])
def test_bad_arguments_give_one_line_and_exit_2(tmp_path, capsys, args, words):
    with pytest.raises(SystemExit) as e:
        ws.main(["--prism", str(BENCH), "--out", str(tmp_path / "o"), *args])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0]
    assert not (tmp_path / "o").exists()
