"""Relay variants of the same first order: what a design's relay lenses cost.

Two variants of an InI design with a coaxial relay (by default ``scenes/ini_wearable.toml``)
whose lenses (named by their front surfaces, ``R1a`` ...) are swapped for
something else with *exactly* the same paraxial matrix, so the first-order
model (CDP, EI pitch, pixel, FOV, tunable-lens powers) is unchanged and only the
lenses' aberrations differ:

* ``ideal``: each singlet (faces c1, c2, thickness t, index n) becomes two ideal
  thin lenses of powers (n − 1)·c1 and (1 − n)·c2, t/n apart (the reduced
  thickness). Everything placed after the relay by ``global_position`` (the
  prism, the viewing window) moves toward the display by Σ(t − t/n), so every
  reduced distance stays as it was. Ideal lenses image perfectly and carry no
  dispersion: the variant is exact at the primary wavelength.
* ``glass``: each singlet in another glass of index n′: curvatures times
  (n − 1)/(n′ − 1), centre thickness times n′/n (the same reduced thickness),
  and what follows the relay moves away by Σ t(n′/n − 1).

Run ``python examples/relay_variants.py --out DIR`` to write both variants and
print their first-order data against the original. ``--optimize coarse,freeform``
then re-optimizes each variant with those stages of its own schedule and
analyses it (``lfsim analyze --stride 4,2``); docs/optimization.md, "Where the
image is lost", lists what this measured on the wearable design.
"""

from __future__ import annotations

import copy
import json
import subprocess
import sys
import tomllib
from pathlib import Path

import tomli_w

from lfsim.cli import OneLineParser
from lfsim.optics.materials import lookup

ROOT = Path(__file__).resolve().parents[1]
LENSES = ("R1a", "R2a", "R3a", "R4a")


def _curvature(s: dict) -> float:
    return s["curvature"] if "curvature" in s else 1.0 / s["radius"]


def _singlets(raw: dict, lenses):
    """(index of the front face, front table, back table) of each named singlet."""
    S = raw["surfaces"]
    names = [s.get("name") for s in S]
    for name in lenses:
        if name not in names:
            raise ValueError(f"no surface named {name!r}")
        i = names.index(name)
        if i + 1 >= len(S) or str(S[i].get("material", "air")).lower() == "air":
            raise ValueError(f"{name!r} is not the front face of a glass singlet")
        off_axis(S[i], S[i + 1])
        yield i, S[i], S[i + 1]


def off_axis(*faces: dict) -> None:
    """Refuse a decentred or tilted face: these variants (and the paraxial relay search)
    hold a lens's matrix about one axis."""
    for f in faces:
        for key in ("decenter", "tilt"):
            v = f.get(key)
            if v is not None and any(float(x) != 0.0 for x in v):
                raise ValueError(f"surface {f.get('name')!r} {key} = {list(v)}: the relay must be coaxial "
                                 f"(a lens's paraxial matrix about one axis)")


def _shift_after_relay(raw: dict, dz: float) -> None:
    for s in raw["surfaces"]:
        if "global_position" in s:
            g = list(s["global_position"])
            g[2] += dz
            s["global_position"] = g


def _primary(raw: dict) -> float:
    sysd = raw.get("system", {})
    return float(sysd.get("primary_wavelength_nm", (sysd.get("wavelengths_nm") or [587.5618])[0]))


def ideal_relay(raw: dict, lenses=LENSES) -> dict:
    """``raw`` with each named singlet as two ideal lenses of the same paraxial matrix."""
    out = copy.deepcopy(raw)
    lam = _primary(raw)
    shift = 0.0
    swaps = []
    for i, a, b in _singlets(out, lenses):
        n = float(lookup(a["material"]).index(lam))
        c1, c2, t = _curvature(a), _curvature(b), float(a["thickness"])
        keep = {k: a[k] for k in ("semi_diameter", "aperture") if k in a}
        front = {"name": a["name"], "type": "paraxial", "focal_length": 1.0 / ((n - 1.0) * c1) if c1 else float("inf"),
                 "thickness": t / n, **keep,
                 "comment": f"ideal lens: the front face of {a['name']} ({a['material']}, n = {n:.6f} at {lam:g} nm)"}
        keep = {k: b[k] for k in ("semi_diameter", "aperture") if k in b}
        back = {"name": b["name"], "type": "paraxial", "focal_length": 1.0 / ((1.0 - n) * c2) if c2 else float("inf"),
                "thickness": b["thickness"], **keep, "comment": f"ideal lens: the back face of {a['name']}"}
        swaps.append((i, front, back))
        shift += t - t / n
    for i, front, back in swaps:
        out["surfaces"][i], out["surfaces"][i + 1] = front, back
    _shift_after_relay(out, -shift)
    _drop_lens_variables(out, lenses)
    out["name"] = f"{raw.get('name', 'design')} (ideal relay)"
    return out


def reglass_relay(raw: dict, glass: str, lenses=LENSES) -> dict:
    """``raw`` with each named singlet in ``glass``, of the same paraxial matrix."""
    out = copy.deepcopy(raw)
    lam = _primary(raw)
    n_new = float(lookup(glass).index(lam))
    shift = 0.0
    for _, a, b in _singlets(out, lenses):
        n = float(lookup(a["material"]).index(lam))
        k = (n - 1.0) / (n_new - 1.0)
        for s in (a, b):
            c = _curvature(s)
            s.pop("radius", None)
            s["curvature"] = c * k
        t = float(a["thickness"])
        a["thickness"] = t * n_new / n
        shift += a["thickness"] - t
        a["material"] = glass
    _shift_after_relay(out, shift)
    out["name"] = f"{raw.get('name', 'design')} (relay in {glass})"
    return out


def _drop_lens_variables(raw: dict, lenses) -> None:
    """Ideal lenses have no curvature or glass thickness to vary: drop those variables."""
    gone = set()
    for name in lenses:
        gone |= {name, name[:-1] + "b"}
    opt = raw.get("optimize")
    if not opt:
        return

    def keep(v):
        name = v if isinstance(v, str) else v.get("name", "")
        return name.split(".")[0] not in gone

    opt["variables"] = [v for v in opt.get("variables", []) if keep(v)]
    for st in opt.get("stages", []):
        if "variables" in st:
            st["variables"] = [v for v in st["variables"] if keep(v)]


def first_order(path: Path) -> list[dict]:
    """The ``lfsim ini`` states of a design file."""
    import lfsim
    from lfsim.ini.model import IniModel

    model = IniModel(lfsim.load(path))
    return [model.state(k).as_dict() for k in range(len(model.depths))]


def main(argv=None) -> int:
    ap = OneLineParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--design", default=str(ROOT / "scenes" / "ini_wearable.toml"),
                    help="an InI design whose relay singlets are coaxial (default: %(default)s)")
    ap.add_argument("--lenses", default=",".join(LENSES), help="front faces of the relay singlets")
    ap.add_argument("--glass", default="N-LASF31A", help="the glass of the 'glass' variant")
    ap.add_argument("--out", required=True, help="folder for ideal.toml, glass.toml and their runs")
    ap.add_argument("--variants", default="ideal,glass",
                    help="which variants to build: ideal, glass, ideal,glass or both (default: both)")
    ap.add_argument("--optimize", default=None, help="stages to re-optimize each variant with, e.g. coarse,freeform")
    args = ap.parse_args(argv)
    wanted = [v.strip() for v in args.variants.split(",") if v.strip()]
    wanted = ["ideal", "glass"] if wanted == ["both"] else wanted
    if not wanted or set(wanted) - {"ideal", "glass"}:
        ap.error(f"--variants {args.variants!r}: ideal, glass, ideal,glass or both")
    import lfsim

    try:
        raw = tomllib.loads(Path(args.design).read_text())
        lfsim.load(args.design)  # the schema's one-line errors, before anything is written
    except (OSError, tomllib.TOMLDecodeError, ValueError) as e:
        ap.error(f"--design {args.design!r}: {e}")
    if "glass" in wanted:
        try:
            lookup(args.glass)
        except (KeyError, ValueError) as e:
            ap.error(f"--glass {args.glass!r}: {e}")
    if args.optimize:
        known = [st.get("name") for st in raw.get("optimize", {}).get("stages", [])]
        bad = [v for v in args.optimize.split(",") if v.strip() not in known]
        if bad:
            ap.error(f"--optimize {args.optimize!r}: {bad[0].strip()!r} is not a stage of {Path(args.design).name} "
                     f"({', '.join(map(str, known)) or 'it has none'})")
    lenses = tuple(v.strip() for v in args.lenses.split(",") if v.strip())
    build = {"ideal": lambda: ideal_relay(raw, lenses), "glass": lambda: reglass_relay(raw, args.glass, lenses)}
    try:
        variants = {name: build[name]() for name in wanted}
    except (KeyError, ValueError) as e:
        ap.error(f"--lenses {args.lenses!r} in {args.design!r}: {e}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ref = first_order(Path(args.design))
    for name, tab in variants.items():
        p = out / f"{name}.toml"
        p.write_text(tomli_w.dumps(tab))
        states = first_order(p)
        for a, b in zip(ref, states):
            print(f"{name:6s} CDP {a['diopters']:g} D: cdp_x {b['cdp_diopters_x']:.5f} "
                  f"(was {a['cdp_diopters_x']:.5f}) D, "
                  f"p_ei_x {b['p_ei'][0]:.6f} (was {a['p_ei'][0]:.6f}) mm, pixel {b['pixel_arcmin'][0]:.4f}' "
                  f"(was {a['pixel_arcmin'][0]:.4f}'), tunable {b['tunable_power_diopters']:.4f} D")
        if args.optimize:
            run = out / f"{name}_run"
            lf = [sys.executable, "-m", "lfsim.cli"]
            subprocess.run([*lf, "optimize", str(p), "--out", str(run), "--stages", args.optimize, "--no-analyze"],
                           check=True)
            best = run / f"{name}_optimized.toml"
            subprocess.run([*lf, "analyze", str(best), "--out", str(out / f"{name}_analyze"), "--stride", "4,2"],
                           check=True)
            doc = json.loads((out / f"{name}_analyze" / "metrics.json").read_text())
            print(f"{name}: " + json.dumps({k: doc["summary"][k] for k in (
                "contrast_nyquist_min", "contrast_nyquist_mean", "gd_max_deg", "pa_max", "rms_spot_mean_arcmin")}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
