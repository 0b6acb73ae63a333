"""Kernels depend on a design's structure, never on its numbers or on counts.

Dr.Jit compiles a kernel per distinct IR; a Python number in an expression is
a literal of that IR. These tests run a workload twice, the second time on a
design whose every number differs (or with another ray / column count), and
read ``dr.kernel_history()``: the second run must compile nothing.
"""

from __future__ import annotations

import copy
import tomllib

import drjit as dr
import numpy as np
import pytest

import lfsim
from lfsim.design.design import Design
from lfsim.ini import subsystems
from lfsim.ini.model import IniModel


def _raw(path):
    with open(path, "rb") as f:
        return tomllib.load(f)


def _perturbed(raw: dict, rel: float) -> dict:
    """A copy whose surface, object and array floats move by ``rel`` (relative; 0 → +rel)."""
    out = copy.deepcopy(raw)

    def walk(d):
        for k, v in d.items():
            if isinstance(v, bool) or k in ("material", "name"):
                continue
            if isinstance(v, float) and np.isfinite(v):
                d[k] = v * (1.0 + rel) if v != 0.0 else rel
            elif isinstance(v, dict):
                walk(v)

    for s in out.get("surfaces", []):
        walk(s)
    for key in ("object", "arrays"):
        if key in out:
            walk(out[key])
    return out


def _compiled(run) -> int:
    """Number of kernels ``run()`` had to compile (not found in a kernel cache)."""
    dr.eval()
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # clear
        run()
        dr.sync_thread()
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return sum(1 for k in hist if not (k["cache_hit"] or k["cache_disk"]))


def _trace_bundle(design):
    rng = np.random.default_rng(1)
    n = 257
    o = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-3, 3, n), np.full(n, -5.0)])
    d = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.1, 0.1, n), np.ones(n)])
    return design.trace(o, d)


def test_design_trace_compiles_once_for_any_numbers(scenes):
    raw = _raw(scenes / "cooke_triplet.toml")
    a = Design.from_dict(raw, "a.toml")
    b = Design.from_dict(_perturbed(raw, 0.013), "b.toml")
    assert b.system.surfaces[0].curvature != a.system.surfaces[0].curvature
    _trace_bundle(a)
    assert _compiled(lambda: _trace_bundle(b)) == 0


def _ini_workload(design):
    model = IniModel(design)
    subs = subsystems.sample(model, stride=(8, 4), symmetry="none", depths=[0])
    rho = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, -0.5], [0.3, 0.3]])
    b = subsystems.trace(model, subs, rho)
    assert b.ok.mean() > 0.5
    return model, b


@pytest.mark.parametrize("scene", ["ini_freeform.toml", "ini_coaxial.toml"])
def test_ini_model_and_subsystem_trace_compile_once_for_any_numbers(scenes, scene):
    raw = _raw(scenes / scene)
    a = Design.from_dict(raw, "a.toml")
    b = Design.from_dict(_perturbed(raw, 2e-4), "b.toml")
    ma, _ = _ini_workload(a)
    mb = None

    def run():
        nonlocal mb
        mb, _ = _ini_workload(b)

    assert _compiled(run) == 0
    assert not np.allclose(ma.values0, mb.values0)


def test_jacobian_compiles_once_for_any_column_and_ray_count(scenes):
    model = IniModel(lfsim.load(scenes / "ini_ideal.toml"))  # small kernels; the same code as any design
    names = [n for n in model.tracer.names if n.endswith((".power", ".thickness", ".tilt_x", ".decenter_y"))]
    rng = np.random.default_rng(3)

    def jac(cols, nrays):
        s = model.lenslet_center(8, 4) + rng.uniform(-0.1, 0.1, (nrays, 2))  # the centre lenslet
        rho = rng.uniform(-0.5, 0.5, (nrays, 2))
        return subsystems.trace_rays_jacobian(model, s, 8, 4, rho, 0, [(n, None) for n in cols])

    j1 = jac(names[:5], 7)
    assert j1.d_pos.shape == (7, 2, 5)
    assert _compiled(lambda: jac(names[:9], 11)) == 0


def test_vector_width_changes_no_result(scenes):
    """Each lane's arithmetic is the same at any LLVM vector width (compact kernels,
    ``LFSIM_VECTOR_WIDTH``): traces, first-order data and aimed bundles agree bit for bit."""
    from lfsim import backend

    if backend.vector_width() is None:
        pytest.skip("CPU back end only")
    design = lfsim.load(scenes / "freeform_prism.toml")
    ini = lfsim.load(scenes / "ini_coaxial.toml")
    old = backend.vector_width()
    results = []
    try:
        for w in (8, 4):
            backend._llvm_target().set_width(w)
            r = _trace_bundle(design)
            fo = design.first_order()
            model, b = _ini_workload(ini)
            results.append((r.positions, r.directions, r.opl, r.status, fo.efl, model.JG, b.pos, b.dir, b.opl))
    finally:
        backend._llvm_target().set_width(old)
    for a, b in zip(*results):
        np.testing.assert_array_equal(a, b)



_RENDER_AND_COUNT = """
import sys
import drjit as dr
from lfsim.cli import main
from lfsim.render import mitsuba
mitsuba()
dr.set_flag(dr.JitFlag.KernelHistory, True)
assert main(sys.argv[1:]) == 0
jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
print("COMPILED", sum(1 for k in jit if not (k["cache_hit"] or k["cache_disk"])))
"""


def test_a_focal_stack_rendered_again_compiles_nothing(scenes, tmp_path):
    """A second and third `lfsim focal-stack` (new processes, the kernel cache warm) compile
    nothing: no kernel may depend on more than the design's structure and the settings.

    One way they did: Dr.Jit maps a numpy buffer without copying, and a kernel that reads
    it states the buffer's alignment in its IR, so it compiled again whenever numpy
    allocated differently (6-9 kernels of a warm focal stack, measured with the default
    design and a reused output folder). Numpy inputs now go through
    ``backend.from_numpy`` (aligned copies). Whether a given run's heap shows that is up to
    its allocations, so this test guards the property, not every way to break it."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, HOME=str(tmp_path / "home"))
    counts = []
    for _ in range(3):
        args = ["focal-stack", str(scenes / "ini_ideal.toml"), "--content", str(scenes / "fig9_wall.toml"),
                "--spp", "4", "--resolution", "96,56", "--out", str(tmp_path / "out")]  # one folder, replaced
        p = subprocess.run([sys.executable, "-c", _RENDER_AND_COUNT, *args], env=env, capture_output=True,
                           text=True, timeout=600)
        assert p.returncode == 0, p.stderr[-2000:]
        counts.append(int(p.stdout.rsplit("COMPILED", 1)[1]))
    assert counts[0] > 0 and counts[1:] == [0, 0], counts


def test_package_figures_compile_once_for_any_numbers(scenes):
    """The package's edge thicknesses evaluate sags at each lens's semi-diameter: a radius that
    entered the kernel as a literal compiled a kernel per lens and per design."""
    from lfsim.ini.package import package

    raw = _raw(scenes / "ini_coaxial.toml")
    a = Design.from_dict(raw, "a.toml")
    b = Design.from_dict(_perturbed(raw, 3e-4), "b.toml")
    pa = package(IniModel(a))
    pb = None

    def run():
        nonlocal pb
        pb = package(IniModel(b))

    assert _compiled(run) == 0
    assert pb["min_edge_thickness_mm"] != pa["min_edge_thickness_mm"]


def test_ini_trace_at_another_wavelength_compiles_nothing(scenes):
    """Lateral colour, the polychromatic contrast and --ei-colour trace the same design at
    other wavelengths: the glass indices are data, not constants of the kernels."""
    design = Design.from_dict(_raw(scenes / "ini_coaxial.toml"), "a.toml")
    _ini_workload(design)
    subs = subsystems.sample(IniModel(design), stride=(8, 4), symmetry="none", depths=[0])
    rho = np.array([[0.0, 0.0], [0.5, 0.0], [0.0, -0.5], [0.3, 0.3]])
    out = {}

    def run():
        for lam in (486.1327, 656.2725):
            out[lam] = subsystems.trace(IniModel(design, wavelength_nm=lam), subs, rho)

    assert _compiled(run) == 0
    assert not np.allclose(out[486.1327].pos, out[656.2725].pos)  # the glass disperses
