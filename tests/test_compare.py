"""lfsim compare: PSNR, SSIM, per-channel RMSE, largest error, heat maps; exit codes."""

import json
import math

import numpy as np
import OpenEXR
import pytest

from lfsim.analysis.compare import compare_images
from lfsim.cli import main


def _exr(path, channels: dict):
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}) as f:
        f.write(str(path))
    return path


@pytest.fixture
def image():
    rng = np.random.default_rng(0)
    return rng.random((40, 64, 3)).astype(np.float32)


def test_identical_images_ssim_1_infinite_psnr(tmp_path, image, capsys):
    a = _exr(tmp_path / "a.exr", {"RGB": image})
    b = _exr(tmp_path / "b.exr", {"RGB": image.copy()})
    out = tmp_path / "cmp"
    assert main(["compare", str(a), str(b), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["psnr"] is None and doc["identical"] is True  # JSON has no infinity: null = identical
    assert doc["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert doc["rmse"] == 0 and doc["max_abs"] == 0
    assert doc["rmse_channels"] == {"R": 0.0, "G": 0.0, "B": 0.0}
    r = compare_images(image, image.copy())
    assert math.isinf(r["psnr"]) and r["psnr"] > 0 and r["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert json.loads((out / "compare.json").read_text())["psnr"] is None
    assert (out / "heatmap.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_known_difference(tmp_path, image, capsys):
    other = image.copy()
    other[..., 0] += 0.1  # R only
    other[5, 7, 2] += 0.5  # one B pixel
    a = _exr(tmp_path / "a.exr", {"RGB": image})
    b = _exr(tmp_path / "b.exr", {"RGB": other})
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["rmse_channels"]["R"] == pytest.approx(0.1, rel=1e-5)
    assert doc["rmse_channels"]["G"] == 0
    assert doc["rmse_channels"]["B"] == pytest.approx(0.5 / math.sqrt(image[..., 0].size), rel=1e-5)
    assert doc["max_abs"] == pytest.approx(0.5, rel=1e-5)
    mse = (0.1 ** 2 * image[..., 0].size + 0.5 ** 2) / image.size
    rng = float(image.max() - image.min())
    assert doc["psnr"] == pytest.approx(10 * math.log10(rng ** 2 / mse), rel=1e-5)
    assert 0 < doc["ssim"] < 1
    # limits: exit 1 when one is missed, 0 when met
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--min-psnr", "60"]) == 1
    assert "FAILED: PSNR" in capsys.readouterr().out
    assert main(["compare", str(a), str(b), "--out", str(tmp_path / "o"), "--min-ssim", "0.1",
                 "--max-abs", "0.6"]) == 0


def test_focal_stack_folders_are_matched_by_name(tmp_path, image, capsys):
    for d, shift in (("x", 0.0), ("y", 0.02)):
        (tmp_path / d).mkdir()
        _exr(tmp_path / d / "display_750mm.exr", {"RGB": image + shift})
        _exr(tmp_path / d / "natural_750mm.exr", {"RGB": image})
    out = tmp_path / "cmp"
    assert main(["compare", str(tmp_path / "x"), str(tmp_path / "y"), "--out", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    names = [im["name"] for im in doc["images"]]
    assert names == ["display_750mm.exr", "natural_750mm.exr"]
    assert doc["worst"] == "display_750mm.exr" and doc["rmse"] == pytest.approx(0.02, rel=1e-4)
    assert doc["images"][1]["psnr"] is None
    assert (out / "heatmap_display_750mm.png").is_file() and (out / "heatmap_natural_750mm.png").is_file()


@pytest.mark.parametrize("case", ["size", "channels", "unreadable", "missing", "file_vs_folder", "folder_missing"])
def test_bad_input_exits_2_with_one_line(tmp_path, image, capsys, case):
    a = _exr(tmp_path / "a.exr", {"RGB": image})
    if case == "size":
        b, named = _exr(tmp_path / "b.exr", {"RGB": image[:30]}), "b.exr"
    elif case == "channels":
        b, named = _exr(tmp_path / "b.exr", {"Y": image[..., 0]}), "b.exr"
    elif case == "unreadable":
        b, named = tmp_path / "b.exr", "b.exr"
        b.write_text("not an image")
    elif case == "missing":
        b, named = tmp_path / "nothere.exr", "nothere.exr"
    elif case == "file_vs_folder":
        b, named = tmp_path, str(tmp_path)
    else:
        (tmp_path / "p").mkdir()
        (tmp_path / "q").mkdir()
        _exr(tmp_path / "p" / "one.exr", {"RGB": image})
        _exr(tmp_path / "p" / "two.exr", {"RGB": image})
        _exr(tmp_path / "q" / "one.exr", {"RGB": image})
        a, b, named = tmp_path / "p", tmp_path / "q", "two.exr"
    out = tmp_path / "out"
    assert main(["compare", str(a), str(b), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lfsim: error: ") and err.count("\n") == 1 and named in err, err
    assert "Traceback" not in err
    assert not out.exists()  # nothing written


def test_png_is_read_as_linear_values(tmp_path):
    """A PNG (sRGB, 8 bit) of a linear image compares with the image's EXR to the 8-bit
    quantization (the largest linear step between codes, at the top, is 0.0089)."""
    from lfsim.analysis.compare import read_image
    from lfsim.render.focal_stack import write_exr, write_png

    rng = np.random.default_rng(2)
    img = rng.uniform(0.0, 1.0, (24, 32, 3)).astype(np.float32)
    write_exr(tmp_path / "a.exr", img, {})
    write_png(tmp_path / "a.png", img)
    png, names = read_image(tmp_path / "a.png")
    assert names == ["R", "G", "B"] and png.shape == img.shape
    assert np.max(np.abs(png - img)) <= 0.0090
    assert np.mean(np.abs(png - img)) < 0.002  # rounding, not a gamma error (that would be ~0.1)
    doc = compare_images(read_image(tmp_path / "a.exr")[0], png)
    assert doc["psnr"] > 45


def test_exposure_matched_ssim_sees_structure_not_brightness():
    """A dimmed copy of an image: SSIM well under 1, exposure the dimming, matched SSIM 1; a
    blurred copy keeps a matched SSIM under 1 (the structure's loss is not scaled away)."""
    from lfsim.metrics.image import exposure, ssim, ssim_matched

    rng = np.random.default_rng(3)
    ref = rng.random((40, 50, 3))
    assert ssim(ref, 0.35 * ref) < 0.6
    assert exposure(ref, 0.35 * ref) == pytest.approx(0.35, rel=1e-12)
    assert ssim_matched(ref, 0.35 * ref) == pytest.approx(1.0, abs=1e-12)
    blur = 0.35 * (ref + np.roll(ref, 1, axis=0) + np.roll(ref, 1, axis=1)) / 3
    assert ssim_matched(ref, blur) < 0.9
    assert exposure(ref, np.zeros_like(ref)) is None and ssim_matched(ref, np.zeros_like(ref)) is None
