"""Image comparison: PSNR, SSIM, per-channel RMSE, largest error and a heat map.

Plain functions on arrays (float images, ``(H, W, C)``) plus the readers
behind ``lfsim compare A B``: two EXR files, or two folders of EXRs (e.g.
two focal stacks), matched by file name. The first image (``A``) is the
reference: its value range is the data range of PSNR and SSIM.

This module only compares; it never renders. The noise-aware statistics of
regression tests (several Monte Carlo seeds) are in :mod:`lfsim.regression.noise`.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

# One convention for every similarity lfsim reports.
from ..metrics.image import data_range, psnr, ssim  # noqa: F401 (part of this module's API)

#: Rec. 709 luminance weights (linear RGB).
LUMA = np.array([0.2126, 0.7152, 0.0722])


class CompareInputError(ValueError):
    """An input that cannot be compared (unreadable, not an EXR, mismatched size or channels)."""


# ------------------------------------------------------------------ reading
def read_image(path) -> tuple[np.ndarray, list[str]]:
    """An EXR (or a PNG) as ``(pixels (H, W, C) float64, channel names)``.

    OpenEXR groups R, G, B (and A) into one ``RGB`` / ``RGBA`` channel; other
    channels are stacked in name order. A PNG (8 or 16 bit, sRGB encoded) is
    decoded to linear values in [0, 1] by Mitsuba's bitmap conversion, so it
    compares in the same units as a rendered EXR (to its quantization).

    Raises
    ------
    CompareInputError
        The file is missing, is not a readable EXR/PNG, or its channels differ in size.
    """
    import OpenEXR

    p = Path(path)
    if not p.is_file():
        raise CompareInputError(f"{p}: no such file")
    if p.suffix.lower() == ".png":
        return _read_png(p)
    try:
        with OpenEXR.File(str(p)) as f:
            channels = {k: np.asarray(v.pixels) for k, v in f.channels().items()}
    except Exception as e:  # OpenEXR raises RuntimeError for anything it cannot read
        raise CompareInputError(f"{p}: not a readable EXR image ({' '.join(str(e).split())})") from None
    # The image is its RGB(A) layer where it has one: other layers are AOVs (lfsim's elemental
    # images carry depth.Z and normal beside RGB), not what an image comparison compares.
    image = [k for k in ("RGBA", "RGB") if k in channels]
    if image:
        channels = {image[0]: channels[image[0]]}
    names, planes = [], []
    for key in sorted(channels):
        arr = channels[key]
        if arr.ndim == 2:
            names.append(key)
            planes.append(arr[..., None])
        elif arr.ndim == 3 and key in ("RGB", "RGBA") and arr.shape[2] == len(key):
            names.extend(key)
            planes.append(arr)
        else:
            raise CompareInputError(f"{p}: channel {key!r} has an unexpected shape {arr.shape}")
    if not planes:
        raise CompareInputError(f"{p}: the EXR has no channels")
    shapes = {a.shape[:2] for a in planes}
    if len(shapes) != 1:
        raise CompareInputError(f"{p}: channels of different sizes {sorted(shapes)}")
    img = np.concatenate(planes, axis=2).astype(np.float64)
    if not np.all(np.isfinite(img)):
        raise CompareInputError(f"{p}: non-finite pixel values (NaN or inf)")
    return img, names


def _read_png(p: Path) -> tuple[np.ndarray, list[str]]:
    from ..render import mitsuba

    mi = mitsuba()
    try:
        bmp = mi.Bitmap(str(p))
    except Exception as e:  # Mitsuba raises RuntimeError for anything it cannot read
        raise CompareInputError(f"{p}: not a readable PNG image ({' '.join(str(e).split())})") from None
    fmt = bmp.pixel_format()
    names = {mi.Bitmap.PixelFormat.Y: "Y", mi.Bitmap.PixelFormat.YA: "YA", mi.Bitmap.PixelFormat.RGB: "RGB",
             mi.Bitmap.PixelFormat.RGBA: "RGBA"}.get(fmt)
    if names is None:
        raise CompareInputError(f"{p}: unsupported PNG pixel format {fmt}")
    lin = bmp.convert(fmt, mi.Struct.Type.Float32, srgb_gamma=False)
    img = np.array(lin, dtype=np.float64).reshape(bmp.height(), bmp.width(), len(names))
    return img, list(names)


def check_compatible(a: np.ndarray, b: np.ndarray, name_a="A", name_b="B", channels_a=None, channels_b=None):
    """Raise :class:`CompareInputError` unless two images have the same size and channels."""
    if a.shape[:2] != b.shape[:2]:
        raise CompareInputError(f"{name_b}: size {b.shape[1]}x{b.shape[0]} px differs from "
                                f"{name_a}: {a.shape[1]}x{a.shape[0]} px")
    ca = channels_a if channels_a is not None else [str(i) for i in range(a.shape[2])]
    cb = channels_b if channels_b is not None else [str(i) for i in range(b.shape[2])]
    if list(ca) != list(cb):
        raise CompareInputError(f"{name_b}: channels {','.join(cb)} differ from {name_a}: {','.join(ca)}")




def compare_images(ref: np.ndarray, img: np.ndarray, channels: list[str] | None = None) -> dict:
    """PSNR (dB; ``inf`` when identical), SSIM, RMSE (all and per channel), largest absolute error.

    ``ref`` and ``img`` are ``(H, W, C)`` (or ``(H, W)``) arrays of the same
    shape, in the same (linear) units; the data range is ``ref``'s.
    """
    ref = np.asarray(ref, np.float64)
    img = np.asarray(img, np.float64)
    if ref.ndim == 2:
        ref, img = ref[..., None], img[..., None]
    check_compatible(ref, img)
    channels = list(channels) if channels is not None else [str(i) for i in range(ref.shape[2])]
    rng = data_range(ref)
    d = img - ref
    return {
        "psnr": psnr(ref, img, rng),
        "ssim": ssim(ref, img, rng),
        "rmse": float(np.sqrt(np.mean(d * d))),
        "rmse_channels": {c: float(np.sqrt(np.mean(d[..., i] ** 2))) for i, c in enumerate(channels)},
        "max_abs": float(np.max(np.abs(d))),
        "mean_abs": float(np.mean(np.abs(d))),
        "mean_ref": float(np.mean(ref)),
        "data_range": rng,
        "identical": bool(np.array_equal(ref, img)),
        "size": [int(ref.shape[1]), int(ref.shape[0])],
        "channels": channels,
    }


# ------------------------------------------------------------------ heat map
def _preview(img: np.ndarray) -> np.ndarray:
    """A linear image as an 8-bit-like display preview (clamped, gamma 2.2)."""
    x = np.clip(np.asarray(img, np.float64), 0.0, 1.0) ** (1 / 2.2)
    if x.shape[2] == 1:
        return x[..., 0]
    return x[..., :3] if x.shape[2] >= 3 else x[..., 0]


def heatmap(ref: np.ndarray, img: np.ndarray, path, title: str = "", labels=("A", "B")) -> str:
    """Write ``path`` (PNG, atomically): ``ref``, ``img`` and ``|img − ref|`` (largest over channels).

    Returns the file name.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..fileio import save_figure

    ref = np.asarray(ref, np.float64)
    img = np.asarray(img, np.float64)
    if ref.ndim == 2:
        ref, img = ref[..., None], img[..., None]
    diff = np.max(np.abs(img - ref), axis=2)
    H, W = diff.shape
    aspect = H / W
    fig, axes = plt.subplots(1, 3, figsize=(12.0, 4.0 * aspect + 1.2), squeeze=False)
    for ax, im, lab in zip(axes[0][:2], (ref, img), labels):
        ax.imshow(_preview(im), cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax.set_title(lab, fontsize=9)
    vmax = float(diff.max()) or 1.0
    h = axes[0][2].imshow(diff, cmap="inferno", vmin=0.0, vmax=vmax, interpolation="nearest")
    axes[0][2].set_title("|B − A| (largest over channels)", fontsize=9)
    fig.colorbar(h, ax=axes[0][2], fraction=0.046 * aspect, pad=0.02)
    for ax in axes[0]:
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)
    return Path(path).name


# ------------------------------------------------------------------ files and folders
def _exr_files(folder: Path) -> dict[str, Path]:
    return {p.name: p for p in sorted(folder.glob("*.exr")) if not p.name.startswith(".")}


def pairs(a, b) -> list[tuple[str, Path, Path]]:
    """``[(name, path_a, path_b)]``: two EXR files, or the EXRs of two folders matched by name.

    Raises
    ------
    CompareInputError
        A missing path, a file against a folder, a folder without EXRs, or an
        EXR present in one folder only.
    """
    a, b = Path(a), Path(b)
    for p in (a, b):
        if not p.exists():
            raise CompareInputError(f"{p}: no such file or directory")
    if a.is_dir() != b.is_dir():
        raise CompareInputError(f"{b}: compare two EXR files or two folders, not a file with a folder ({a})")
    if not a.is_dir():
        return [(a.name, a, b)]
    fa, fb = _exr_files(a), _exr_files(b)
    if not fa:
        raise CompareInputError(f"{a}: no EXR images in the folder")
    for x, fx, y, fy in ((a, fa, b, fb), (b, fb, a, fa)):
        missing = sorted(set(fx) - set(fy))
        if missing:
            raise CompareInputError(f"{y / missing[0]}: missing (present in {x}; "
                                    f"{len(missing)} image(s) only in one folder)")
    return [(n, fa[n], fb[n]) for n in sorted(fa)]


def limit_failures(doc: dict, min_psnr=None, min_ssim=None, max_abs=None) -> list[str]:
    """The limits a comparison misses, as one-line texts (empty: all met)."""
    out = []
    if min_psnr is not None and doc["psnr"] < min_psnr:
        out.append(f"PSNR {_fmt_psnr(doc['psnr'])} < {min_psnr:g} dB ({doc['worst']})")
    if min_ssim is not None and doc["ssim"] is not None and doc["ssim"] < min_ssim:
        out.append(f"SSIM {doc['ssim']:.4f} < {min_ssim:g}")
    if max_abs is not None and doc["max_abs"] > max_abs:
        out.append(f"max |B-A| {doc['max_abs']:.4g} > {max_abs:g}")
    return out


def compare_paths(a, b, out_dir=None, log=None, limits: dict | None = None) -> dict:
    """Compare two EXRs or two folders of EXRs; write heat maps and ``compare.json`` to ``out_dir``.

    Returns ``{"psnr", "ssim", "rmse", "max_abs", …, "images": [...]}``: for
    folders the summary figures are the worst over the images (lowest PSNR and
    SSIM, largest RMSE and error), ``worst`` names the image with the lowest
    PSNR. ``limits`` (``min_psnr``, ``min_ssim``, ``max_abs``): the ones missed
    are listed in ``failed``. Every image is read and checked before anything
    is written; ``out_dir`` is a folder replaced as a whole on success (see
    :func:`lfsim.fileio.atomic_dir`).
    """
    import contextlib

    from ..fileio import atomic_dir, write_json

    with atomic_dir(out_dir, "compare.json") if out_dir is not None else contextlib.nullcontext() as tmp:
        return _compare_paths(a, b, tmp, log, limits, write_json)


def _compare_paths(a, b, out_dir, log, limits, write_json) -> dict:
    items = pairs(a, b)
    loaded = []
    for name, pa, pb in items:
        ia, ca = read_image(pa)
        ib, cb = read_image(pb)
        check_compatible(ia, ib, str(pa), str(pb), ca, cb)
        loaded.append((name, pa, pb, ia, ib, ca))
    images = []
    for name, pa, pb, ia, ib, ca in loaded:
        rec = {"name": name, "a": str(pa), "b": str(pb), **compare_images(ia, ib, ca)}
        if out_dir is not None:
            stem = "heatmap" if len(loaded) == 1 else f"heatmap_{Path(name).stem}"
            title = (f"{name}: PSNR {_fmt_psnr(rec['psnr'])}, SSIM {_fmt(rec['ssim'])}, "
                     f"RMSE {rec['rmse']:.4g}, max |B−A| {rec['max_abs']:.4g}")
            rec["heatmap"] = heatmap(ia, ib, Path(out_dir) / f"{stem}.png", title, labels=(f"A: {pa}", f"B: {pb}"))
        images.append(rec)
        if log:
            log(f"{name}: PSNR {_fmt_psnr(rec['psnr'])}, SSIM {_fmt(rec['ssim'])}")
    worst = min(images, key=lambda r: r["psnr"])
    ssims = [r["ssim"] for r in images if r["ssim"] is not None]
    doc = {
        "a": str(a), "b": str(b),
        "psnr": worst["psnr"],
        "ssim": min(ssims) if ssims else None,
        "rmse": max(r["rmse"] for r in images),
        "max_abs": max(r["max_abs"] for r in images),
        "identical": all(r["identical"] for r in images),
        "worst": worst["name"],
        "images": images,
    }
    doc["failed"] = limit_failures(doc, **(limits or {}))
    if len(images) == 1:
        doc["rmse_channels"] = images[0]["rmse_channels"]
        if "heatmap" in images[0]:
            doc["heatmap"] = images[0]["heatmap"]
    if out_dir is not None:
        write_json(Path(out_dir) / "compare.json", json_safe(doc))
    return doc


def json_safe(obj):
    """``obj`` with infinite floats (PSNR of identical images) as None, for strict JSON."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def _fmt(v) -> str:
    return "-" if v is None else f"{v:.4f}"


def _fmt_psnr(v) -> str:
    return "inf" if v is None or math.isinf(v) else f"{v:.2f} dB"
