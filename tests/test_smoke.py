import numpy as np

import lfsim


def test_cooke_triplet_axial_ray_reaches_image(scenes):
    d = lfsim.load(scenes / "cooke_triplet.toml")
    r = d.trace(np.array([[0.0, 0.0, -5.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert r.status.tolist() == [0]
    np.testing.assert_allclose(r.positions[0], [0, 0, 60.17675], atol=1e-12)
    np.testing.assert_allclose(r.directions[0], [0, 0, 1], atol=1e-15)


def test_design_trace_matches_the_dr_jit_trace_and_checks_its_directions(scenes):
    """The numpy API (gather in, interleaving kernel out) returns what the
    Dr.Jit trace it wraps computes, bit for bit, in (N, 3) float64 / int64
    arrays, and refuses bad directions after its launch."""
    import pytest

    from lfsim.optics.tracer import RayState

    d = lfsim.load(scenes / "ini_coaxial.toml")  # has a lenslet array
    rng = np.random.default_rng(3)
    n = 301
    o = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), np.full(n, -d.system.object_distance)])
    v = np.column_stack([rng.uniform(-0.2, 0.2, n), rng.uniform(-0.2, 0.2, n), np.ones(n)])
    r = d.trace(o, v, record=True)
    tr = d.tracer()
    T = tr.T
    ref = tr.trace(tr.params(None), RayState(T.Array3(*(T.Float(o[:, c]) for c in range(3))),
                                             T.Array3(*(T.Float(v[:, c]) for c in range(3)))), record=True)
    for got, want in ((r.positions, ref.p), (r.directions, ref.d)):
        assert got.shape == (n, 3) and got.dtype == np.float64
        np.testing.assert_array_equal(got, np.stack([np.asarray(want[c]) for c in range(3)], axis=1))
    np.testing.assert_array_equal(r.status, np.asarray(ref.status))
    np.testing.assert_array_equal(r.failed_at, np.asarray(ref.failed_at))
    np.testing.assert_array_equal(r.opl, np.asarray(ref.opl))
    np.testing.assert_array_equal(r.lenslet, np.stack([np.asarray(ref.lenslet_m), np.asarray(ref.lenslet_n)], 1))
    assert r.status.dtype == r.failed_at.dtype == r.lenslet.dtype == np.int64
    assert (r.status == 0).any() and (r.status != 0).any()
    assert (r.lenslet >= 0).any()
    assert r.path.shape == (len(d.system.surfaces), n, 3)
    np.testing.assert_array_equal(r.path[-1], r.positions)
    for bad, msg in (([0.0, 0.0, 0.0], "zero vector"), ([np.nan, 0.0, 1.0], "non-finite")):
        v2 = v.copy()
        v2[7] = bad
        with pytest.raises(ValueError, match=msg):
            d.trace(o, v2)
