"""Zemax OpticStudio lens files (``.zmx``, sequential): reader and writer.

Reader: UTF-16 (with its byte-order mark) or UTF-8 text; ``SURF`` blocks of type
``STANDARD``, ``EVENASPH``, ``XYPOLYNOM``, ``COORDBRK`` and ``PARAXIAL`` into an lfsim design
table. Supported, refused and ignored keywords are listed in ``docs/lens-files.md``.

Conventions (pinned by ``tests/test_lensfiles.py``):

* ``DIAM`` (semi-diameter) becomes ``semi_diameter``, which clips rays in lfsim; ``CLAP``
  (circular), ``SQAP`` (rectangular half-widths) and ``FLAP`` become ``aperture`` tables,
  ``OBDC`` their decenter.
* ``COORDBRK``: ``PARM 1, 2`` decenter x, y; ``PARM 3, 4, 5`` tilts about x, y, z (degrees);
  ``PARM 6`` the order flag: 0 = decenter, then tilt about x, the new y, the new z (lfsim's
  own order); otherwise tilt about z, y, x, then decenter. Zemax tilts about x and y turn
  the left-handed way like CODE V's α and β: lfsim ``tilt = [−tx, −ty, tz]``.
* ``EVENASPH``: ``PARM 2`` … ``PARM 8`` are A4 … A16 (``PARM 1``, the r² term, must be 0).
* ``XYPOLYNOM``: ``XDAT 1`` the number of terms, ``XDAT 2`` the normalization radius,
  ``XDAT 3`` … the terms x, y, x², xy, y², x³, … (Zemax's order), like lfsim's ``xy``.
* ``PARAXIAL``: ``PARM 1`` the focal length: an lfsim ideal lens.
* ``GLAS ___BLANK 1 0 nd vd``: a model glass {nd, vd}; vd = 0 a constant index.
* ``GLAS name``: as in Zemax, the glass of the first ``GCAT`` vendor that has the name; the
  writer lists the vendors so that each name is taken from the one with the design's indices.
"""

from __future__ import annotations

import math
from pathlib import Path

from .codev import _XY_OF_J, xy_index
from .common import (
    INFINITE_DISTANCE,
    UNITS_MM,
    Imported,
    LensFileError,
    check_complete,
    finite,
    fmt,
    material_value,
    note_defaults,
    scale_lengths,
)

#: Zemax (tilt x, tilt y, tilt z) → lfsim tilt factors.
TILT_SIGN = (-1.0, -1.0, 1.0)
_SURFACE_IGNORED = {"HIDE", "MIRR", "SLAB", "POPS", "MAZH", "COAT", "FIMP", "MEMA", "OEMA", "PZUP", "VPAR",
                    "PPAR", "VCON", "EDGE", "TCED", "VDSZ", "BLNK", "MNCA", "MNEA", "MNCG", "MNEG", "MXCA",
                    "MXCG", "RGLA", "UDAD", "FLOA", "NSCD", "TOLE", "CURV_SOLVE", "THIC", "ISNA", "IGNR"}
_TOP_IGNORED = {"VERS", "NOTE", "AUTH", "PFIL", "LANG", "ENVD", "GFAC", "RAIM", "PUSH", "SDMA", "OMMA", "ROPD",
                "HYPR", "PICB", "POLS", "GLRS", "GSTD", "NSCD", "COFN", "BLNK", "TOL", "MOFF", "FWGN", "FWGT",
                "VDXN", "VDYN", "VCXN", "VCYN", "VANN", "DMFS", "TRAC", "ACOS", "GLCB", "RCMF", "EFLY", "EFLX",
                "REAY", "REAX", "WFNO", "OPDX", "DBDT", "TCMM", "PMAG", "TOTR", "ZVDX", "ZVDY", "ZVCX", "ZVCY",
                "ZVAN", "WWGN", "WWGT", "WAVN", "BLOF", "PUPD", "EFFL", "CONF", "TOLE"}


def decode(data: bytes, file: str) -> str:
    if data[:2] in (b"\xff\xfe", b"\xfe\xff"):
        try:
            text = data.decode("utf-16")
        except UnicodeDecodeError:
            raise LensFileError(file, None, "not a Zemax file (bad UTF-16 text)") from None
    elif data[:3] == b"\xef\xbb\xbf":
        text = data[3:].decode("utf-8", errors="replace")
    else:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError:
            text = data.decode("latin-1")
    if "\x00" in text:
        raise LensFileError(file, None, "not a Zemax file (binary data)")
    return text


class _Surf:
    def __init__(self, index, line):
        self.index, self.line = index, line
        self.type = "STANDARD"
        self.curv = 0.0
        self.disz = 0.0
        self.glass = None
        self.glass_line = None
        self.mirror = False
        self.conic = 0.0
        self.parm: dict[int, float] = {}
        self.xdat: dict[int, float] = {}
        self.diam = None
        self.stop = False
        self.comment = ""
        self.ap = None  # ("circular", r) | ("rectangular", hx, hy)
        self.ap_dec = (0.0, 0.0)


def read_zmx(path: str | Path, data: bytes | None = None) -> Imported:
    file = str(path)
    if data is None:
        try:
            data = Path(path).read_bytes()
        except OSError as e:
            raise LensFileError(file, None, f"cannot read file ({e.strerror or e})") from None
    text = decode(data, file)
    check_complete(text, file)
    surfs: list[_Surf] = []
    cur: _Surf | None = None
    title = ""
    unit = "MM"
    aperture = None
    gcat: list[str] = []
    ftyp = None
    ftyp_line = None
    xfln, yfln = [], []
    wavm: dict[int, tuple[float, float]] = {}
    wavl: list[float] = []
    pwav = 1
    notes: list[str] = []
    seen_mode = False

    def num(line, tok, what):
        return finite(file, line, tok, what)

    for ln, rawline in enumerate(text.splitlines(), 1):
        parts = rawline.split()
        if not parts:
            continue
        key = parts[0].upper()
        args = parts[1:]
        rest = rawline.strip()[len(parts[0]):].strip()

        def arg(k, what):
            if len(args) <= k:
                raise LensFileError(file, ln, f"{key}: missing {what}")
            return args[k]

        if key == "SURF":
            idx = int(num(ln, arg(0, "a surface number"), "SURF"))
            if idx != len(surfs):
                raise LensFileError(file, ln, f"SURF {idx}: expected surface {len(surfs)}")
            cur = _Surf(idx, ln)
            surfs.append(cur)
            continue
        if key == "MODE":
            seen_mode = True
            if not args or args[0].upper() != "SEQ":
                raise LensFileError(file, ln, f"MODE {rest}: only sequential files are supported")
            continue
        if key == "NAME":
            title = rest.strip('"')
            continue
        if key == "UNIT":
            if not args or args[0].upper() not in ("MM", "CM", "IN", "METER"):
                raise LensFileError(file, ln, f"UNIT {arg(0, 'a unit')}: expected MM, CM, IN or METER")
            unit = args[0].upper()
            continue
        if key in ("ENPD", "FNUM", "OBNA"):
            v = num(ln, arg(0, "a value"), key)
            aperture = {"ENPD": "epd", "FNUM": "fno", "OBNA": "na"}[key], v, ln
            continue
        if key in ("FLOA", "OBNA_", "ISNA"):
            raise LensFileError(file, ln, f"{key}: this system aperture type is not supported (use ENPD, FNUM "
                                "or OBNA)")
        if key == "GCAT":
            gcat = [a.upper() for a in args]
            continue
        if key == "FTYP":
            ftyp = [int(num(ln, a, "FTYP")) for a in args]
            ftyp_line = ln
            continue
        if key in ("XFLN", "YFLN", "XFLD", "YFLD"):
            vals = [num(ln, a, key) for a in args]
            if key[0] == "X":
                xfln = vals
            else:
                yfln = vals
            continue
        if key == "WAVM":
            k = int(num(ln, arg(0, "a slot"), "WAVM"))
            wavm[k] = (num(ln, arg(1, "a wavelength"), "WAVM"), num(ln, args[2], "WAVM") if len(args) > 2 else 1.0)
            continue
        if key == "WAVL":
            wavl = [num(ln, a, "WAVL") for a in args]
            continue
        if key == "PWAV":
            pwav = int(num(ln, arg(0, "a slot"), "PWAV"))
            continue
        if key == "MNUM":
            if args and int(num(ln, args[0], "MNUM")) > 1:
                raise LensFileError(file, ln, "MNUM: multi-configuration files are not supported")
            continue
        if cur is None or not rawline[:1].isspace():
            if key in _TOP_IGNORED:
                continue
            if cur is None:
                raise LensFileError(file, ln, f"{key}: keyword not supported by lfsim's Zemax reader")
            # unindented keyword after the surfaces: settings
            raise LensFileError(file, ln, f"{key}: keyword not supported by lfsim's Zemax reader")
        # ----- surface data
        s = cur
        if key == "TYPE":
            s.type = arg(0, "a type").upper()
            if s.type not in ("STANDARD", "EVENASPH", "XYPOLYNOM", "COORDBRK", "PARAXIAL"):
                raise LensFileError(file, ln, f"TYPE {s.type}: surface type not supported (STANDARD, EVENASPH, "
                                    "XYPOLYNOM, COORDBRK, PARAXIAL)")
        elif key == "CURV":
            s.curv = num(ln, arg(0, "a curvature"), "CURV")
        elif key == "DISZ":
            t = arg(0, "a thickness")
            s.disz = math.inf if t.upper() in ("INFINITY", "INF") else num(ln, t, "DISZ")
        elif key == "GLAS":
            name = arg(0, "a glass")
            s.glass_line = ln
            if name.upper() == "MIRROR":
                s.mirror = True
            elif name == "___BLANK":
                if len(args) < 5:
                    raise LensFileError(file, ln, "GLAS ___BLANK: expected ___BLANK 1 0 nd vd")
                nd, vd = num(ln, args[3], "nd"), num(ln, args[4], "vd")
                s.glass = nd if vd == 0 else {"nd": nd, "vd": vd}
            else:
                s.glass = name
        elif key == "CONI":
            s.conic = num(ln, arg(0, "a conic"), "CONI")
        elif key == "PARM":
            s.parm[int(num(ln, arg(0, "a number"), "PARM"))] = num(ln, arg(1, "a value"), "PARM")
        elif key == "XDAT":
            s.xdat[int(num(ln, arg(0, "a number"), "XDAT"))] = num(ln, arg(1, "a value"), "XDAT")
        elif key == "DIAM":
            s.diam = num(ln, arg(0, "a semi-diameter"), "DIAM")
        elif key == "STOP":
            s.stop = True
        elif key == "COMM":
            s.comment = rest
        elif key in ("CLAP", "FLAP"):
            lo, hi = num(ln, arg(0, "a radius"), key), num(ln, arg(1, "a radius"), key)
            if lo != 0.0:
                raise LensFileError(file, ln, f"{key} {lo:g} {hi:g}: annular apertures are not supported")
            s.ap = ("circular", hi)
        elif key == "SQAP":
            s.ap = ("rectangular", num(ln, arg(0, "a half-width"), key), num(ln, arg(1, "a half-width"), key))
        elif key == "OBDC":
            s.ap_dec = (num(ln, arg(0, "an offset"), key), num(ln, arg(1, "an offset"), key))
        elif key in ("ELAP", "OBSC", "ELOB", "SQOB", "UDAP", "USAP", "UDOB", "SPID", "SCBD", "TILT", "DECX"):
            raise LensFileError(file, ln, f"{key}: not supported (lfsim reads circular and rectangular clear "
                                "apertures, and coordinate breaks for tilts)")
        elif key in ("PKUP",):
            continue  # a pickup solve: the file carries the value it gave
        elif key in _SURFACE_IGNORED:
            continue
        else:
            raise LensFileError(file, ln, f"{key}: surface keyword not supported by lfsim's Zemax reader")

    if not seen_mode and not surfs:
        raise LensFileError(file, None, "not a Zemax lens file (no MODE, no SURF)")
    if len(surfs) < 3:
        raise LensFileError(file, None, "need an object, at least one surface and an image (SURF 0, 1, 2 ...)")
    raw = _assemble(file, surfs, gcat, notes)
    raw = {"name": title or Path(file).stem, "description": f"Imported from the Zemax file {Path(file).name}",
           **raw}
    sysd: dict = {}
    at_inf = math.isinf(raw["object"]["distance"])
    if aperture:
        if aperture[0] == "na" and at_inf:
            raise LensFileError(file, aperture[2], f"OBNA {aperture[1]:g}: an object-space NA needs a finite "
                                "object, and SURF 0 puts the object at infinity (DISZ INFINITY or >= 1e10); give "
                                "ENPD or FNUM")
        sysd["aperture"] = {"type": aperture[0], "value": aperture[1]}
    nf = ftyp[2] if ftyp and len(ftyp) > 2 and ftyp[2] > 0 else max(len(yfln), len(xfln), 1)
    ys = (yfln or [0.0])[:nf]
    xs = (xfln or [0.0])[:nf]
    ftype = ftyp[0] if ftyp else 0
    if any(v != 0 for v in ys) and ftype not in (0, 1):
        raise LensFileError(file, ftyp_line, f"FTYP {ftype}: field type not supported (0 angle, 1 object height)")
    if ftype == 1 and not at_inf:
        sysd["field"] = {"type": "height", "values": list(dict.fromkeys(ys))}
    else:
        sysd["field"] = {"type": "angle", "values": list(dict.fromkeys(ys))}
    if any(v != 0 for v in xs):
        notes.append("x field components (XFLN) are not kept: lfsim's [system] field lists y fields only")
    if wavl:
        wl = [w * 1000.0 for w in wavl]
        prim = wl[pwav - 1] if 1 <= pwav <= len(wl) else wl[0]
    elif wavm:
        nw = ftyp[3] if ftyp and len(ftyp) > 3 and ftyp[3] > 0 else max(wavm)
        slots = [k for k in sorted(wavm) if k <= nw]
        wl = [wavm[k][0] * 1000.0 for k in slots]
        prim = wavm[pwav][0] * 1000.0 if pwav in wavm else wl[0]
    else:
        wl, prim = [], None
    if wl:
        sysd["wavelengths_nm"] = list(dict.fromkeys(wl))
        sysd["primary_wavelength_nm"] = prim
        if prim not in sysd["wavelengths_nm"]:
            sysd["wavelengths_nm"].append(prim)
    raw["system"] = sysd
    note_defaults(sysd, notes, "ENPD, FNUM or OBNA", "WAVM or WAVL")
    raw = {k: raw[k] for k in ("name", "description", "system", "object", "surfaces")}
    if UNITS_MM[unit] != 1.0:
        notes.append(f"lengths converted from UNIT {unit} to millimetres (x {UNITS_MM[unit]:g})")
    return Imported(scale_lengths(raw, UNITS_MM[unit]), notes)


def _assemble(file, surfs: list[_Surf], gcat, notes) -> dict:
    so = surfs[0]
    obj: dict = {}
    if so.type != "STANDARD" or so.curv != 0.0:
        raise LensFileError(file, so.line, "SURF 0 (the object) must be a flat STANDARD surface")
    d = so.disz
    if math.isinf(d) or d >= INFINITE_DISTANCE:
        obj["distance"] = math.inf
    elif d > 0:
        obj["distance"] = d
    else:
        raise LensFileError(file, so.line, f"DISZ {d!r}: the object must lie before the first surface")
    medium = "air"
    if so.glass is not None:
        medium = obj["material"] = _glass(file, so.glass_line, so.glass, gcat)
    if so.mirror:
        raise LensFileError(file, so.line, "the object surface cannot be a mirror")
    out: list[dict] = []
    last = len(surfs) - 1
    for k, s in enumerate(surfs[1:], 1):
        if s.type == "COORDBRK":
            out.extend(_coordbrk(file, s))
            continue
        tab: dict = {"comment": f"SURF {s.index}" + (f": {s.comment}" if s.comment else "")}
        if s.type == "PARAXIAL":
            f = s.parm.get(1, 0.0)
            if f == 0.0:
                raise LensFileError(file, s.line, "PARAXIAL with PARM 1 = 0: the focal length must be nonzero")
            tab["type"] = "paraxial"
            tab["focal_length"] = f
            if s.glass is not None or s.mirror:
                raise LensFileError(file, s.glass_line, "a PARAXIAL surface with a glass is not supported")
        else:
            tab["curvature"] = s.curv
            if s.conic:
                tab["conic"] = s.conic
            if s.type == "STANDARD":
                for p, v in s.parm.items():
                    if v != 0.0:
                        raise LensFileError(file, s.line, f"PARM {p} = {v!r} on a STANDARD surface")
            elif s.type == "EVENASPH":
                if s.parm.get(1, 0.0) != 0.0:
                    raise LensFileError(file, s.line, "EVENASPH PARM 1 (an r^2 term) is not supported")
                asp = {f"A{2 * p}": v for p, v in sorted(s.parm.items()) if 2 <= p <= 8 and v != 0.0}
                bad = [p for p, v in s.parm.items() if p > 8 and v != 0.0]
                if bad:
                    raise LensFileError(file, s.line, f"EVENASPH PARM {bad[0]}: terms beyond r^16 are not supported")
                if asp:
                    tab["asphere"] = asp
            elif s.type == "XYPOLYNOM":
                xy = {}
                nterm = int(s.xdat.get(1, 0))
                for i, v in sorted(s.xdat.items()):
                    if i < 3 or v == 0.0:
                        continue
                    if i - 2 > nterm:
                        continue
                    j = i - 1  # CODE V's C_j numbering starts at the conic
                    if j not in _XY_OF_J:
                        raise LensFileError(file, s.line, f"XYPOLYNOM XDAT {i}: terms beyond total order 10 are "
                                            "not supported")
                    m, n = _XY_OF_J[j]
                    xy[f"x{m}y{n}"] = v
                for p, v in s.parm.items():
                    if v != 0.0:
                        raise LensFileError(file, s.line, f"XYPOLYNOM PARM {p} = {v!r} is not supported")
                if xy:
                    tab["xy"] = xy
                    R = s.xdat.get(2, 1.0)
                    if not R > 0:
                        raise LensFileError(file, s.line, f"XYPOLYNOM normalization radius {R!r} must be > 0")
                    tab["norm_radius"] = R
            if s.mirror:
                tab["mirror"] = True
            else:
                after = _glass(file, s.glass_line, s.glass, gcat) if s.glass is not None else "air"
                if after == medium:
                    tab["dummy"] = True
                else:
                    tab["material"] = after
                medium = after
        if k == last and "dummy" not in tab and not s.mirror and tab.get("type") != "paraxial":
            pass
        if s.stop:
            tab["stop"] = True
        if s.diam and s.diam > 0 and k != last:
            tab["semi_diameter"] = s.diam
        if s.ap is not None:
            if s.ap[0] == "circular":
                tab["aperture"] = {"type": "circular", "radius": s.ap[1], "decenter": list(s.ap_dec)}
            else:
                tab["aperture"] = {"type": "rectangular", "half_width": [s.ap[1], s.ap[2]],
                                   "decenter": list(s.ap_dec)}
        tab["thickness"] = 0.0 if k == last else s.disz
        if math.isinf(tab["thickness"]):
            raise LensFileError(file, s.line, "DISZ INFINITY is allowed on the object surface only")
        out.append(tab)
    return {"object": obj, "surfaces": out}


def _coordbrk(file, s: _Surf) -> list[dict]:
    p = s.parm
    dx, dy = p.get(1, 0.0), p.get(2, 0.0)
    t = [TILT_SIGN[0] * p.get(3, 0.0), TILT_SIGN[1] * p.get(4, 0.0), TILT_SIGN[2] * p.get(5, 0.0)]
    t = [0.0 if v == 0.0 else v for v in t]
    order = p.get(6, 0.0)
    for k in p:
        if k > 6 and p[k] != 0.0:
            raise LensFileError(file, s.line, f"COORDBRK PARM {k} is not supported")
    if s.glass is not None or s.mirror:
        raise LensFileError(file, s.glass_line, "a COORDBRK with a glass is not supported")
    comment = f"SURF {s.index}: COORDBRK" + (f" {s.comment}" if s.comment else "")
    if order == 0.0:
        tab = {"type": "coordinate_break", "comment": comment}
        if dx or dy:
            tab["decenter"] = [dx, dy]
        if any(t):
            tab["tilt"] = t
        tab["thickness"] = s.disz
        return [tab]
    out = []
    for k in (2, 1, 0):  # tilt about z, then y, then x, then decenter
        if t[k]:
            tt = [0.0, 0.0, 0.0]
            tt[k] = t[k]
            out.append({"type": "coordinate_break", "tilt": tt, "thickness": 0.0, "comment": comment})
    out.append({"type": "coordinate_break", "decenter": [dx, dy], "thickness": s.disz, "comment": comment})
    return out


def _glass(file, line, g, gcat):
    if isinstance(g, (dict, float)):
        return g
    return material_value(file, line, g, tuple(gcat))


# --------------------------------------------------------------------- writer
def zemax_glass(name: str, wavelengths) -> tuple[str, str] | None:
    """A glass as a Zemax catalog spells it, and the vendor whose glass of that name has the
    indices of ``name`` at ``wavelengths``: ``SK16`` → ``("SK16", "HIKARI")``, ``NSSK2_SCHOTT``
    → ``("N-SSK2", "SCHOTT")``; None where no vendor catalog holds it (PMMA, FUSED_SILICA)."""
    from ...optics.glass_catalogs import index, name_key, split_vendor
    from .export import same_index

    base, vendor = split_vendor(name)
    for v, _, _, page in index().get(name_key(base), []):
        if vendor in (None, v) and same_index(f"{page}_{v}", name, wavelengths):
            return page, v
    return None


def _catalog_glasses(plan) -> tuple[dict[str, str], list[str]]:
    """Each named medium's Zemax spelling, and the GCAT vendors: those of the glasses used, each
    before every other listed vendor that holds a glass of the same name (Zemax takes a GLAS name
    from the first GCAT catalog that has it), else in the order of ``VENDORS``."""
    from ...optics.glass_catalogs import VENDORS, index, name_key

    used: dict[str, tuple[str, str, str]] = {}  # name: (where, page, vendor)
    for where, g in [("the object space", plan.object_glass)] + [(f"surface {e.name}", e.glass)
                                                                 for e in plan.entries if not e.mirror]:
        if isinstance(g, str) and g not in used:
            hit = zemax_glass(g, plan.system.wavelengths_nm)
            if hit is None:
                raise ValueError(f"{where}: material {g!r} is in no vendor catalog, so no Zemax GLAS name gives "
                                 "its indices (a ___BLANK model glass has another dispersion); give the design a "
                                 "vendor catalog glass or a model glass {nd, vd}")
            used[g] = (where, *hit)
    vendors = [v for v in VENDORS if any(u[2] == v for u in used.values())]
    # the other listed vendors that hold a glass of the name: GCAT must list them after its own
    later = {g: {w for w, *_ in index()[name_key(page)]} & set(vendors) - {v} for g, (_, page, v) in used.items()}
    order: list[str] = []
    while len(order) < len(vendors):
        left = [v for v in vendors if v not in order]
        free = [v for v in left if not any(v in later[g] and u[2] in left for g, u in used.items())]
        if not free:
            clash = [(w, g, page, v) for g, (w, page, v) in used.items() if v in left and later[g] & set(left)]
            raise ValueError("; ".join(f"{w} {g!r} ({page} of {v})" for w, g, page, v in clash) + ": Zemax takes a "
                             "GLAS name from the first GCAT catalog that has it, and no order of "
                             f"{', '.join(dict.fromkeys(c[3] for c in clash))} gives each its own; use glasses of "
                             "distinct names")
        order.append(free[0])
    return {g: u[1] for g, u in used.items()}, order


def _glass_line(g, spell) -> str:
    if isinstance(g, dict):
        if "n" in g:
            return f"GLAS ___BLANK 1 0 {fmt(g['n'])} 0 0 0 0 0 0 0"
        return f"GLAS ___BLANK 1 0 {fmt(g['nd'])} {fmt(g['vd'])} 0 0 0 0 0 0"
    return f"GLAS {spell[g]} 0 0 0 0 0 0 0 0 0 0"


def write_zmx(plan, title: str) -> str:
    sysd = plan.system
    L = ["VERS 190513 80 123457", "MODE SEQ", f"NAME {title}", "UNIT MM X W X CM MR CPMM"]
    if sysd.aperture_type == "epd":
        L.append(f"ENPD {fmt(sysd.aperture_value)}")
    elif sysd.aperture_type == "fno":
        L.append(f"FNUM {fmt(sysd.aperture_value)} 0")
    else:
        L.append(f"OBNA {fmt(sysd.aperture_value)} 0")
    from ...optics.glass_catalogs import VENDORS

    spell, gcat = _catalog_glasses(plan)
    L.append("GCAT " + " ".join(gcat or VENDORS[:3]))
    wl = sysd.wavelengths_nm
    L.append(f"FTYP {0 if sysd.field_type == 'angle' else 1} 0 {len(sysd.fields)} {len(wl)} 0 0 0")
    L.append("XFLN " + " ".join("0" for _ in sysd.fields))
    L.append("YFLN " + " ".join(fmt(f) for f in sysd.fields))
    for k, w in enumerate(wl, 1):
        L.append(f"WAVM {k} {fmt(w / 1000.0)} 1")
    prim = sysd.primary_wavelength_nm
    if prim in wl:
        L.append(f"PWAV {wl.index(prim) + 1}")
    d = sysd.object_distance
    L += ["SURF 0", "  TYPE STANDARD", "  CURV 0.0", f"  DISZ {'INFINITY' if math.isinf(d) else fmt(d)}"]
    if plan.object_glass is not None:
        L.append("  " + _glass_line(plan.object_glass, spell))
    for k, e in enumerate(plan.entries, 1):
        L.append(f"SURF {k}")
        L += ["  " + x for x in _surface(e, spell)]
    return "\n".join(L) + "\n"


def _surface(e, spell) -> list[str]:
    out = [f'COMM {e.name}']
    if e.kind == "break":
        dx, dy, dz, tx, ty, tz = e.decenter or (0.0,) * 6
        out += ["TYPE COORDBRK", "CURV 0.0", f"PARM 1 {fmt(dx)}", f"PARM 2 {fmt(dy)}",
                f"PARM 3 {fmt(TILT_SIGN[0] * tx + 0.0)}", f"PARM 4 {fmt(TILT_SIGN[1] * ty + 0.0)}",
                f"PARM 5 {fmt(TILT_SIGN[2] * tz + 0.0)}", "PARM 6 0", f"DISZ {fmt(e.thickness)}"]
        return out
    if e.stop:
        out.append("STOP")
    if e.kind == "paraxial":
        if math.isinf(e.focal_length):
            out += ["TYPE STANDARD", "CURV 0.0"]
        else:
            out += ["TYPE PARAXIAL", "CURV 0.0", f"PARM 1 {fmt(e.focal_length)}", "PARM 2 1"]
    elif e.xy:
        if e.asphere:
            raise ValueError(f"surface {e.name}: Zemax's XYPOLYNOM surface has no even-asphere terms")
        terms = {xy_index(m, n) - 1: c for (m, n), c in e.xy.items()}
        out += ["TYPE XYPOLYNOM", f"CURV {fmt(e.curvature)}", f"XDAT 1 {max(terms)} 0 0 0 0 0 \"\"",
                f"XDAT 2 {fmt(e.norm_radius)} 0 0 0 0 0 \"\""]
        for t in range(1, max(terms) + 1):
            out.append(f"XDAT {t + 2} {fmt(terms.get(t, 0.0))} 0 0 0 0 0 \"\"")
    elif e.asphere:
        out += ["TYPE EVENASPH", f"CURV {fmt(e.curvature)}", "PARM 1 0"]
        for o in range(4, 17, 2):
            out.append(f"PARM {o // 2} {fmt(e.asphere.get(o, 0.0))}")
    else:
        out += ["TYPE STANDARD", f"CURV {fmt(e.curvature)}"]
    out.append(f"DISZ {fmt(0.0 if e.image else e.thickness)}")
    if e.mirror:
        out.append("GLAS MIRROR 0 0 0 0 0 0 0 0 0 0")
    elif e.glass is not None:
        out.append(_glass_line(e.glass, spell))
    if e.conic:
        out.append(f"CONI {fmt(e.conic)}")
    if e.semi_diameter is not None:
        out.append(f'DIAM {fmt(e.semi_diameter)} 1 0 0 1 ""')
    ap = e.aperture
    if ap is not None and not (e.semi_diameter is not None and ap.kind == "circular"
                               and ap.radius == e.semi_diameter and not any(ap.decenter)):
        if ap.kind == "circular":
            out.append(f"CLAP 0 {fmt(ap.radius)} 0")
        else:
            out.append(f"SQAP {fmt(ap.half_width[0])} {fmt(ap.half_width[1])} 0")
        if any(ap.decenter):
            out.append(f"OBDC {fmt(ap.decenter[0])} {fmt(ap.decenter[1])}")
    return out
