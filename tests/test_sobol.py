"""The retinal cameras' sampler (lfsim.render.sobol): Owen-scrambled Sobol points per pixel."""

import numpy as np
import pytest

from lfsim.render import mitsuba
from lfsim.render.eye import sampler_type
from lfsim.render.sobol import DIMENSIONS, sobol_table


def draw(kind: str, spp: int, pixels: int, dims: int, seed: int = 0) -> np.ndarray:
    """(pixels, spp, dims) numbers from a sampler seeded as a render seeds it."""
    mi = mitsuba()
    sampler_type(spp)  # registers lfsim_sobol
    s = mi.load_dict({"type": kind, "sample_count": spp, "seed": seed})
    s.set_samples_per_wavefront(spp)
    s.seed(0, pixels * spp)
    out = np.stack([np.asarray(s.next_1d()) for _ in range(dims)], axis=-1)
    return out.reshape(pixels, spp, dims)


def test_every_sample_count_is_kept():
    mi = mitsuba()
    for n in (1, 7, 50, 64, 100, 256):
        assert mi.load_dict({"type": sampler_type(n), "sample_count": n}).sample_count() == n


def test_table_is_the_sobol_sequence():
    t = sobol_table(8, 3) / 2.0**32
    # Sobol's first points: 0, 1/2, then (3/4, 1/4, 1/4), (1/4, 3/4, 3/4), ...
    assert np.allclose(t[:, :4].T, [[0, 0, 0], [0.5, 0.5, 0.5], [0.75, 0.25, 0.25], [0.25, 0.75, 0.75]])


def test_each_dimension_is_stratified_per_pixel():
    """An Owen-scrambled net is a net: in every pixel, every dimension puts one of its 64 points
    in each interval [k/64, (k+1)/64), and film x, y one in each of the 64 cells of every
    elementary shape (2^a x 2^b, a + b = 6)."""
    u = draw("lfsim_sobol", 64, 200, 9)
    assert u.min() >= 0.0 and u.max() < 1.0
    cells = np.floor(u * 64).astype(int)
    for d in range(9):
        assert all(len(set(cells[p, :, d])) == 64 for p in range(200)), d
    for a in range(7):
        ix = np.floor(u[..., 0] * 2**a).astype(int) * 2 ** (6 - a) + np.floor(u[..., 1] * 2 ** (6 - a)).astype(int)
        assert all(len(set(ix[p])) == 64 for p in range(200)), a


def test_pixels_and_seeds_are_independent_and_uniform():
    u = draw("lfsim_sobol", 16, 4096, 7)
    v = draw("lfsim_sobol", 16, 4096, 7, seed=1)
    # Each number is uniform: mean 1/2, variance 1/12 over all pixels (4096 x 16 numbers).
    assert np.allclose(u.mean(axis=(0, 1)), 0.5, atol=0.01)
    assert np.allclose(u.var(axis=(0, 1)), 1 / 12, atol=0.002)
    # No two pixels (or seeds) share their points; neighbouring pixels are uncorrelated.
    assert not np.allclose(u[0], u[1]) and not np.allclose(u, v)
    r = np.corrcoef(u[:-1, :, 2].ravel(), u[1:, :, 2].ravel())[0, 1]
    assert abs(r) < 0.02


def test_joint_stratification_beats_padded_and_independent_samplers():
    """Indicators that couple film and pupil coordinates, as the display point an eye ray lands
    on does (to first order a sum of film and pupil offsets): the jointly scrambled Sobol points
    integrate them with a smaller error than Mitsuba's padded multijitter (which stratifies film
    and pupil each on its own) and than independent samples (whose error is sqrt(p(1-p)/spp))."""
    cases = {"ridge": (lambda u: u[..., 0] + 0.5 * u[..., 2] < 0.75, 0.5),
             "disk": (lambda u: (u[..., 0] - 0.5) ** 2 + (u[..., 2] - 0.5) ** 2 < 0.1, 0.1 * np.pi)}
    for name, (f, exact) in cases.items():
        err = {}
        for kind in ("lfsim_sobol", "multijitter", "independent"):
            est = f(draw(kind, 64, 2000, 4)).mean(axis=1)
            err[kind] = float(np.sqrt(np.mean((est - exact) ** 2)))
        assert err["independent"] == pytest.approx(np.sqrt(exact * (1 - exact) / 64), rel=0.1), name
        assert err["lfsim_sobol"] < 0.7 * err["multijitter"] < 0.7 * err["independent"], (name, err)
    assert DIMENSIONS >= 7


def test_sampler_beyond_its_dimensions_and_before_seeding():
    mi = mitsuba()
    sampler_type(4)
    u = draw("lfsim_sobol", 4, 1000, DIMENSIONS + 2)
    assert np.allclose(u[..., -1].mean(), 0.5, atol=0.03)
    s = mi.load_dict({"type": "lfsim_sobol", "sample_count": 4})
    with pytest.raises(RuntimeError, match="seed"):
        s.next_1d()
