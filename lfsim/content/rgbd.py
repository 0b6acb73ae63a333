"""RGB-D content: an image and its depth map as a textured, self-luminous height field.

A content TOML object::

    [[objects]]                # required: image, depth, depth_convention, fov_deg
    type = "rgbd"
    image = "photo.png"        # colour: PNG/JPEG (sRGB, decoded to linear) or EXR (linear)
    depth = "photo_depth.exr"  # depth map, the image's size: EXR (float) or 8/16-bit PNG (raw counts)
    depth_convention = "z"     # "z": distance along the line of sight (-z, planar depth);
                               # "range": distance from the eye along the pixel's ray
    depth_scale_mm = 1.0       # mm per stored depth unit (a 16-bit PNG in 0.1 mm: 0.1)
    fov_deg = 40.0             # horizontal field of the capturing pinhole camera, which sits
                               # at the eye (visual-space origin) and looks along -z
    radiance = 1.0             # scale (or [r, g, b])
    max_jump = 0.05            # a triangle spanning a relative depth jump above this is left
                               # out (no skin between foreground and background)
    stride = 1                 # one mesh vertex every `stride` pixels

Depth 0 (or not finite) marks a pixel without data: triangles touching it are
left out. Pixels are square; the vertical field follows from the image's
aspect. Each vertex sits at its pixel centre's depth along that pixel's ray,
so a pinhole at the eye sees exactly the image, and an eye that focuses sees
each part of it at its own depth. The radiance is the image (self-luminous, no
lighting): shading is the first hit's emission, exact and noise-free, like
the quads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..design.errors import MISSING, DesignError

CONVENTIONS = ("z", "range")


@dataclass
class RgbdObject:
    name: str
    image_path: str
    depth_path: str
    convention: str
    depth_scale_mm: float
    fov_deg: float
    radiance: tuple[float, float, float]
    max_jump: float = 0.05
    stride: int = 1

    def image(self) -> np.ndarray:
        """Linear RGB (H, W, 3) float32."""
        from ..backend import mitsuba

        mi = mitsuba()
        bmp = mi.Bitmap(self.image_path).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                                                 srgb_gamma=False)
        return np.array(bmp, dtype=np.float32)

    def depth_mm(self) -> np.ndarray:
        """Depth (H, W) float64 in mm (0: no data), in this object's convention."""
        return read_depth(self.depth_path) * self.depth_scale_mm

    def points(self, depth: np.ndarray | None = None) -> np.ndarray:
        """Visual-space points (H, W, 3) of every pixel centre at its depth."""
        d = self.depth_mm() if depth is None else depth
        H, W = d.shape
        dirs = pixel_directions(W, H, self.fov_deg)
        if self.convention == "range":
            dirs = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
        return dirs * d[..., None]

    def mesh(self):
        """The height field as a Mitsuba mesh dict entry (an area emitter textured by the image)."""
        from ..backend import mitsuba

        mi = mitsuba()
        img = self.image() * np.asarray(self.radiance, dtype=np.float32)
        depth = self.depth_mm()
        if img.shape[:2] != depth.shape:
            raise DesignError(self.image_path, "", None, f"the image is {img.shape[1]}x{img.shape[0]} px, its depth "
                              f"map {self.depth_path} {depth.shape[1]}x{depth.shape[0]}: they must match")
        H, W = depth.shape
        s = self.stride
        rows, cols = np.arange(0, H, s), np.arange(0, W, s)
        P = self.points(depth)[np.ix_(rows, cols)]
        D = depth[np.ix_(rows, cols)]
        h, w = D.shape
        uv = np.stack(np.meshgrid((cols + 0.5) / W, (rows + 0.5) / H), axis=-1)
        ok = np.isfinite(D) & (D > 0)
        idx = np.arange(h * w).reshape(h, w)
        a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
        Df = np.where(ok, D, np.nan).ravel()
        tris = []
        for t in (np.stack([a, c, b], -1), np.stack([b, c, d], -1)):  # front (u x v) toward the eye
            t = t.reshape(-1, 3)
            z = Df[t]
            good = np.all(np.isfinite(z), axis=1)
            zz = np.where(good[:, None], z, 1.0)
            good &= zz.max(axis=1) <= (1.0 + self.max_jump) * zz.min(axis=1)
            tris.append(t[good])
        F = np.concatenate(tris).astype(np.uint32)
        if len(F) == 0:
            raise DesignError(self.depth_path, "", None, "the depth map gives no triangle (no data, or every "
                              "step a jump above max_jump)")
        V = np.where(ok.ravel()[:, None], P.reshape(-1, 3), 0.0).astype(np.float32)
        props = mi.Properties()
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {
            "type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(img)), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "clamp"}})
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}})
        mesh = mi.Mesh(self.name, len(V), len(F), props, False, True)
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(np.ascontiguousarray(V.ravel()))
        p["faces"] = mi.UInt32(np.ascontiguousarray(F.ravel()))
        p["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uv.reshape(-1, 2).astype(np.float32).ravel()))
        p.update()
        return mesh


def pixel_directions(W: int, H: int, fov_deg: float) -> np.ndarray:
    """Directions (H, W, 3) through pixel centres of a pinhole at the origin looking along -z,
    scaled to z = -1 (row 0 at the top, square pixels)."""
    t = math.tan(math.radians(fov_deg) / 2.0)
    x = ((np.arange(W) + 0.5) / W * 2.0 - 1.0) * t
    y = (1.0 - (np.arange(H) + 0.5) / H * 2.0) * t * H / W
    X, Y = np.meshgrid(x, y)
    return np.stack([X, Y, -np.ones_like(X)], axis=-1)


def read_depth(path: str) -> np.ndarray:
    """The stored values (H, W) float64 of a depth map: an EXR's first channel, or a PNG's raw counts."""
    p = Path(path)
    if p.suffix.lower() == ".exr":
        import OpenEXR

        with OpenEXR.File(str(p)) as f:
            ch = f.channels()
            key = next((k for k in ("Z", "depth.Z", "Y", "depth", "R", "RGB") if k in ch), next(iter(ch)))
            a = np.asarray(ch[key].pixels, dtype=np.float64)
    else:
        from skimage.io import imread

        a = np.asarray(imread(str(p)), dtype=np.float64)
    if a.ndim == 3:
        a = a[..., 0]
    return a


def _file(file, key, v, base: Path) -> str:
    if not isinstance(v, str) or not v:
        raise DesignError(file, key, v, "expected an image file path (relative to this file)")
    full = (base / v).resolve()
    if not full.is_file():
        raise DesignError(file, key, v, f"no such file ({full})")
    return str(full)


def parse_rgbd(file: str, key: str, o: dict, base: Path, i: int) -> RgbdObject:
    """An ``[[objects]]`` table of type ``rgbd`` (module docstring)."""
    from .schema import _num, _rgb, no_unknown

    allowed = {"type", "name", "image", "depth", "depth_convention", "depth_scale_mm", "fov_deg", "radiance",
               "max_jump", "stride"}
    no_unknown(file, f"{key}.", o, allowed)
    for req in ("image", "depth", "depth_convention", "fov_deg"):
        if req not in o:
            raise DesignError(file, f"{key}.{req}", MISSING, "required for an rgbd object (module docs: "
                              "image, depth, depth_convention, fov_deg)")
    conv = o.get("depth_convention")
    if conv not in CONVENTIONS:
        raise DesignError(file, f"{key}.depth_convention", conv,
                          "expected \"z\" (distance along the line of sight) or \"range\" (distance from the eye)")
    fov = _num(file, f"{key}.fov_deg", o.get("fov_deg"), positive=True)
    if not fov < 170.0:
        raise DesignError(file, f"{key}.fov_deg", fov, "expected a horizontal field in (0, 170) degrees")
    stride = o.get("stride", 1)
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise DesignError(file, f"{key}.stride", stride, "expected an integer >= 1")
    obj = RgbdObject(str(o.get("name", f"object{i}")), _file(file, f"{key}.image", o.get("image"), base),
                     _file(file, f"{key}.depth", o.get("depth"), base), conv,
                     _num(file, f"{key}.depth_scale_mm", o.get("depth_scale_mm", 1.0), positive=True), fov,
                     _rgb(file, f"{key}.radiance", o.get("radiance", 1.0)),
                     _num(file, f"{key}.max_jump", o.get("max_jump", 0.05), positive=True), stride)
    d = obj.depth_mm()
    if not np.any(np.isfinite(d) & (d > 0)):
        raise DesignError(file, f"{key}.depth", o.get("depth"), "the depth map holds no depth > 0")
    if np.any(d < 0):
        raise DesignError(file, f"{key}.depth", o.get("depth"), f"negative depths (min {np.nanmin(d):.4g} mm): "
                          "depth is a distance in front of the eye")
    return obj
