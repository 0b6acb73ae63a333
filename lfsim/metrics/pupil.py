"""Pupil samples on a lenslet's square stop, in units of its half-widths (ρ ∈ [−1, 1]²)."""

from __future__ import annotations

import numpy as np


def gauss_legendre_square(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Tensor Gauss–Legendre rule of ``n × n`` nodes on [−1, 1]².

    Returns nodes (n², 2) and weights (n²,) summing to 1 (a mean over the
    square pupil). Exact for polynomials of degree ≤ 2n − 1 in each variable,
    so pupil integrals of smooth aberrations converge spectrally.
    """
    x, w = np.polynomial.legendre.leggauss(int(n))
    X, Y = np.meshgrid(x, x, indexing="xy")
    W = np.outer(w, w) / 4.0
    return np.stack([X.ravel(), Y.ravel()], axis=1), W.ravel()


def mtf_grid(n: int) -> np.ndarray:
    """``n × n`` cell centres of the square pupil (row-major, y slowest): the FFT grid."""
    v = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    X, Y = np.meshgrid(v, v, indexing="xy")
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def perimeter(per_side: int) -> np.ndarray:
    """Points on the square pupil's edge, counter-clockwise from (1, −1); ``4·per_side`` points."""
    t = np.linspace(-1.0, 1.0, per_side, endpoint=False)
    right = np.stack([np.ones_like(t), t], axis=1)
    top = np.stack([-t, np.ones_like(t)], axis=1)
    left = np.stack([-np.ones_like(t), -t], axis=1)
    bottom = np.stack([t, -np.ones_like(t)], axis=1)
    return np.concatenate([right, top, left, bottom])


#: The four marginal rays of Eq. (12): the midpoints of the stop's edges (+x, −x, +y, −y).
MARGINAL = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
