"""Verbs of a conventional optical system: `trace`, `first-order`, `params`, `layout`."""

from __future__ import annotations

import csv
import io
import math
import sys

import numpy as np

from ..fileio import write_text
from .common import InputError, _add_set, _dump, _fmt, _load_design

RAY_COLUMNS = ("x", "y", "z", "dx", "dy", "dz")


def read_rays_csv(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Rays from a CSV with columns x,y,z,dx,dy,dz (header required)."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except OSError as e:
        raise InputError(f"{path}: cannot read rays file ({e.strerror or e})") from None
    rows = [r for r in rows if r and not r[0].lstrip().startswith("#")]
    if not rows:
        raise InputError(f"{path}: empty rays file: expected a header x,y,z,dx,dy,dz and rows")
    header = [h.strip() for h in rows[0]]
    for c in RAY_COLUMNS:
        if c not in header:
            raise InputError(f"{path}: column {c!r} missing: the header must name x,y,z,dx,dy,dz")
    idx = [header.index(c) for c in RAY_COLUMNS]
    data = np.empty((len(rows) - 1, 6))
    for r, row in enumerate(rows[1:], start=2):
        for k, (c, j) in enumerate(zip(RAY_COLUMNS, idx)):
            try:
                v = float(row[j])
            except (IndexError, ValueError):
                val = row[j] if j < len(row) else ""
                raise InputError(f"{path}: line {r} column {c!r} = {val!r}: expected a number") from None
            if not (math.isfinite(v) and abs(v) <= 1e15):  # the design files' bound (lfsim.design.loader.MAX_ABS)
                raise InputError(f"{path}: line {r} column {c!r} = {row[j]!r}: expected a finite number, |x| <= 1e15")
            data[r - 2, k] = v
    if len(data) == 0:
        raise InputError(f"{path}: no rays after the header")
    zero = np.where(np.linalg.norm(data[:, 3:], axis=1) == 0)[0]
    if len(zero):
        raise InputError(f"{path}: line {zero[0] + 2} direction (dx,dy,dz) = (0,0,0): must be nonzero")
    return data[:, :3], data[:, 3:]


def cmd_trace(args) -> int:
    from ..optics.tracer import Status

    design = _load_design(args)
    o, d = read_rays_csv(args.rays)
    r = design.trace(o, d, wavelength_nm=args.wavelength_nm, precision=args.precision)
    arrays = bool(design.system.arrays)  # lenslet (m, n) columns only where there is an array
    if args.json:
        rows = []
        for i in range(len(o)):
            row = {"position": r.positions[i].tolist(), "direction": r.directions[i].tolist(),
                   "status": int(r.status[i]), "status_name": Status(int(r.status[i])).name.lower(),
                   "opl": float(r.opl[i])}
            if arrays:
                row["lenslet"] = r.lenslet[i].tolist()
            rows.append(row)
        print(_dump({
            "design": design.path, "wavelength_nm": args.wavelength_nm or design.system.primary_wavelength_nm,
            "precision": args.precision, "rays": rows,
        }))
    else:
        buf = io.StringIO()
        lam = args.wavelength_nm or design.system.primary_wavelength_nm
        buf.write(f"# {design.name} at {lam:g} nm, {args.precision}; x,y,z in mm (global frame, at the last "
                  "surface); dx,dy,dz direction cosines; opl optical path length in mm; status: "
                  + ", ".join(f"{int(st)} {st.name.lower()}" for st in Status) + "\n")
        w = csv.writer(buf)
        w.writerow(["x", "y", "z", "dx", "dy", "dz", "status", "status_name", "opl"] + (["m", "n"] if arrays else []))
        for i in range(len(o)):
            st = int(r.status[i])
            w.writerow([f"{v:.15g}" for v in (*r.positions[i], *r.directions[i])]
                       + [st, Status(st).name.lower(), f"{r.opl[i]:.15g}"]
                       + (r.lenslet[i].tolist() if arrays else []))
        if args.out:
            write_text(args.out, buf.getvalue())
        else:
            sys.stdout.write(buf.getvalue())
    return 0


def cmd_first_order(args) -> int:
    design = _load_design(args)
    fo = design.first_order(args.wavelength_nm, method=args.method)
    d = fo.as_dict()
    if args.json:
        print(_dump({"design": design.path, **d}))
    else:
        print(f"{design.name} ({design.path}) at {fo.wavelength_nm:g} nm, {fo.method}")
        for k, v in d.items():
            if k in ("wavelength_nm", "method"):
                continue
            # None: not finite (an afocal system's EFL, an F-number without an entrance pupil)
            text = _fmt(v, ".10g", fo.UNITS.get(k, "")) if v is None or isinstance(v, float) else str(v)
            print(f"  {k:26s} {text}")
    return 0


def cmd_params(args) -> int:
    design = _load_design(args)
    lam = design.wavelength(None)
    rows = [{"name": n, "value": v, "unit": u} for n, v, u in design.parameters(lam)]
    if args.json:  # JSON has no NaN/inf: such a value (none is expected) is written as null
        rows = [{**r, "value": r["value"] if math.isfinite(r["value"]) else None} for r in rows]
        print(_dump({"design": design.name, "file": args.design, "wavelength_nm": lam, "params": rows}))
        return 0
    print(f"# {design.name}: design vector, indices at {lam:g} nm")
    for r in rows:
        print(f"{r['name']:28s} {r['value']: .12g} {r['unit']}")
    return 0


def cmd_lens(args) -> int:
    from ..optics.lens_table import format_table, lens_table

    design = _load_design(args)
    lam = design.wavelength(args.wavelength_nm)
    doc = lens_table(design.system, lam)
    if args.json:
        print(_dump({"design": design.name, "file": args.design, **doc}))
    else:
        print(format_table(doc, design.name))
    return 0


def cmd_layout(args) -> int:
    from ..analysis.layout import layout_report

    design = _load_design(args)
    summary = layout_report(design, args.out)
    if args.json:
        print(_dump(summary))
    elif "ini" in summary:
        from .ini import _first_order_line, _package_line

        ini = summary["ini"]
        print(f"{design.name}: InI design, {ini['lenslets'][0]} x {ini['lenslets'][1]} lenslets, display gap "
              f"{ini['display_gap_mm']:.3f} mm; drawn at CDP {ini['drawn_cdp_diopters']:g} D")
        for D, fo in ini["first_order"].items():
            print(f"  CDP {D} D:" + _first_order_line(fo)[1:])
        print("  " + _package_line(summary["package"]))
        print("  (per-lenslet spots, MTF, GD and PA: lfsim analyze)")
        print(f"wrote {args.out}/layout.png, summary.json")
    else:
        fo = summary["first_order"]
        print(f"{design.name}: EFL {_fmt(fo['efl'], '.6f', 'mm')}, BFL {_fmt(fo['bfl'], '.6f', 'mm')}, "
              f"F/# {_fmt(fo['fno'], '.4f')}")
        unit = "°" if design.system.field_type == "angle" else " mm"
        for row in summary["spots"]:
            rms = "vignetted" if row["rms_um"] is None else f"RMS spot {row['rms_um']:.3f} µm"
            print(f"  field {row['field']:g}{unit}: {rms}")
        print(f"wrote {args.out}/layout.png, spots.png, summary.json")
    return 0


def cmd_import(args) -> int:
    from pathlib import Path

    from ..design.lensfiles import write_imported
    from ..fileio import check_writable

    if Path(args.out).suffix.lower() != ".toml":
        raise InputError(f"--out = {args.out!r}: the design file must end in .toml")
    check_writable(args.out, "--out")
    imp = write_imported(args.file, args.out)
    n = len(imp.raw["surfaces"])
    if args.json:
        print(_dump({"file": args.file, "design": args.out, "surfaces": n, "notes": imp.notes}))
        return 0
    for note in imp.notes:
        print(f"lfsim import: note: {note}", file=sys.stderr)
    print(f"{Path(args.file).name}: {n} surfaces -> {args.out}")
    return 0


def register(sub) -> None:
    """Add this module's verbs to the `lfsim` sub-command parser."""
    t = sub.add_parser("trace", help="trace rays from a CSV through a design")
    t.add_argument("design")
    t.add_argument("--rays", required=True, help="CSV with columns x,y,z,dx,dy,dz (global frame, mm)")
    t.add_argument("--wavelength-nm", type=float, default=None)
    t.add_argument("--precision", choices=("float64", "float32"), default="float64")
    t.add_argument("--out", help="write the CSV here (atomically) instead of stdout")
    _add_set(t)
    t.add_argument("--json", action="store_true")
    t.set_defaults(func=cmd_trace)

    f = sub.add_parser("first-order", help="first-order (paraxial / parabasal) properties")
    f.add_argument("design")
    f.add_argument("--wavelength-nm", type=float, default=None)
    f.add_argument("--method", choices=("auto", "paraxial", "parabasal"), default="auto")
    _add_set(f)
    f.add_argument("--json", action="store_true")
    f.set_defaults(func=cmd_first_order)

    pa = sub.add_parser("params", help="every design number by name (the names --set and [optimize] take)")
    pa.add_argument("design")
    _add_set(pa)
    pa.add_argument("--json", action="store_true")
    pa.set_defaults(func=cmd_params)

    ln = sub.add_parser("lens", help="the lens data table: one row per surface (type, radius, thickness, "
                        "material with nd and Vd, semi-diameter, conic, aspheric and XY terms, tilts, stop)")
    ln.add_argument("design")
    ln.add_argument("--wavelength-nm", type=float, default=None,
                    help="wavelength of the n column, nm (default: the design's primary)")
    _add_set(ln)
    ln.add_argument("--json", action="store_true", help="the same data as JSON")
    ln.set_defaults(func=cmd_lens)

    im = sub.add_parser("import", help="read a CODE V .seq or Zemax .zmx lens file into a design file")
    im.add_argument("file", help="FILE.seq (CODE V) or FILE.zmx (Zemax, UTF-16 or UTF-8)")
    im.add_argument("--out", required=True, help="the design file to write (.toml, atomically; an existing "
                    "file is replaced, missing folders are made); bad input: one line, exit 2, nothing written")
    im.add_argument("--json", action="store_true", help="print the file, design, surface count and notes as JSON")
    im.set_defaults(func=cmd_import)

    lay = sub.add_parser("layout", help="layout and spot-diagram pictures plus a summary")
    lay.add_argument("design")
    lay.add_argument("--out", required=True, help="output directory")
    _add_set(lay)
    lay.add_argument("--json", action="store_true")
    lay.set_defaults(func=cmd_layout)
