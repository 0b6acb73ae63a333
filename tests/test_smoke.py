import numpy as np

import lfsim


def test_cooke_triplet_axial_ray_reaches_image(scenes):
    d = lfsim.load(scenes / "cooke_triplet.toml")
    r = d.trace(np.array([[0.0, 0.0, -5.0]]), np.array([[0.0, 0.0, 1.0]]))
    assert r.status.tolist() == [0]
    np.testing.assert_allclose(r.positions[0], [0, 0, 60.17675], atol=1e-12)
    np.testing.assert_allclose(r.directions[0], [0, 0, 1], atol=1e-15)
