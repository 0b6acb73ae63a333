"""Self-luminous content in Mitsuba: textured quads (and RGB-D height fields) in visual space.

The loaded :class:`~lfsim.content.ContentScene` becomes a Mitsuba scene
in the viewing-window frame. It is shaded in two ways: by the elemental-image
generator (one ray per display pixel, :func:`shade`) and by the eye sensor for
the natural view (the ground truth a display render is compared with).
"""

from __future__ import annotations

import numpy as np

from ..backend import from_numpy, mitsuba
from .schema import ContentScene, Quad


def texture_image(q: Quad) -> np.ndarray:
    """The quad's texture as a linear RGB array (rows: top = +v end, columns: +u)."""
    t = q.texture
    lu, lv = float(np.linalg.norm(q.u)), float(np.linalg.norm(q.v))
    if t.kind == "image":
        # Mitsuba decodes sRGB (PNG, JPEG) to linear; EXR stays linear.
        mi = mitsuba()
        bmp = mi.Bitmap(t.params["path"]).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                                                    srgb_gamma=False)
        return np.array(bmp, dtype=np.float32)
    if t.kind == "constant":
        return np.ones((2, 2, 3), dtype=np.float32)
    if t.kind == "noise":
        from skimage.filters import gaussian

        texel = t.params["texel_mm"]
        w, h = max(2, int(round(lu / texel))), max(2, int(round(lv / texel)))
        rng = np.random.default_rng(t.params["seed"])
        g = gaussian(rng.standard_normal((h, w)), sigma=t.params["feature_mm"] / (2.0 * texel))
        img = (g > np.median(g)).astype(np.float32)
    else:
        per = t.params["period_mm"]
        texel = per / 16.0
        w, h = max(2, int(round(lu / texel))), max(2, int(round(lv / texel)))
        x = (np.arange(w) + 0.5) * lu / w
        y = (np.arange(h) + 0.5) * lv / h
        X, Y = np.meshgrid(x, y[::-1])
        if t.kind == "checker":
            img = ((np.floor(X / (0.5 * per)) + np.floor(Y / (0.5 * per))) % 2).astype(np.float32)
        else:
            img = (np.floor(X / (0.5 * per)) % 2).astype(np.float32)
    return np.repeat(img[..., None], 3, axis=-1)


def quad_transform(q: Quad):
    """``to_world`` of Mitsuba's rectangle ([−1, 1]², normal +z) onto the quad."""
    mi = mitsuba()
    u, v = q.u, q.v
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    c = q.corners[0] + 0.5 * (u + v)
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = 0.5 * u, 0.5 * v, n, c
    return mi.ScalarTransform4f(M.tolist())


def scene_dict(content: ContentScene) -> dict:
    """Mitsuba scene dict of the content (no sensor, no integrator)."""
    mi = mitsuba()
    d = {"type": "scene"}
    if content.scene is not None:
        raise ValueError(f"{content.path}: a Mitsuba scene is path-traced content, which this verb does not "
                         "render (it takes quads and RGB-D objects); lfsim focal-stack renders it")
    for i, q in enumerate(content.objects):
        if not isinstance(q, Quad):  # an RGB-D height field (lfsim.content.rgbd)
            d[f"content_{i}_{q.name}"] = q.mesh()
            continue
        img = texture_image(q) * np.asarray(q.radiance, dtype=np.float32)
        d[f"content_{i}_{q.name}"] = {
            "type": "rectangle",
            "to_world": quad_transform(q),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
            "emitter": {"type": "area",
                        "radiance": {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(img[::-1])),
                                     "raw": True, "filter_type": "bilinear", "wrap_mode": "clamp"}},
        }
    if any(v > 0 for v in content.background):
        d["background"] = {"type": "constant", "radiance": {"type": "rgb", "value": list(content.background)}}
    return d


def shade(scene, origins: np.ndarray, directions: np.ndarray, valid: np.ndarray | None = None,
          background=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Radiance (N, 3) seen along rays (visual-space numpy (N, 3) origins/directions).

    The first object hit gives its emitted radiance; rays that meet nothing
    get ``background``; rays with ``valid`` False get 0.
    """
    import drjit as dr

    mi = mitsuba()
    o = np.asarray(origins, dtype=np.float32)
    dd = np.asarray(directions, dtype=np.float32)
    # Copied into Dr.Jit's aligned memory: a kernel reading a mapped numpy buffer bakes its
    # alignment into the IR and compiles again whenever numpy allocates differently.
    ray = mi.Ray3f(mi.Point3f(*from_numpy(mi.Float, *(o[:, k] for k in range(3)))),
                   dr.normalize(mi.Vector3f(*from_numpy(mi.Float, *(dd[:, k] for k in range(3))))))
    si = scene.ray_intersect(ray)
    L = si.emitter(scene).eval(si, si.is_valid())
    bg = mi.Color3f(*[float(b) for b in background])
    L = dr.select(si.is_valid(), L, bg)
    out = np.stack([np.asarray(L[i]) for i in range(3)], axis=1).astype(np.float32)
    if valid is not None:
        out[~np.asarray(valid, dtype=bool)] = 0.0
    return out
