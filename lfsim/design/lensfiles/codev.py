"""CODE V sequence files (``.seq``): reader and writer.

Reader: the lens-entry commands of a saved CODE V lens (``LEN`` … ``GO``) into an lfsim
design table. Writer: an lfsim system as such a file. Supported, refused and ignored
commands are listed in ``docs/lens-files.md``.

Conventions (pinned by ``tests/test_lensfiles.py`` against closed forms and rayoptics):

* ``RDM`` (radius mode, the default) takes surface values as radii, ``RDM N`` as curvatures.
* ``SI`` thickness is a defocus added to the thickness before the image.
* Decenters: ``XDE``/``YDE``/``ZDE`` then tilts ``ADE`` (α, about x), ``BDE`` (β, about the
  new y), ``CDE`` (γ, about the new z). CODE V's α and β turn the left-handed way, γ the
  right-handed way, so lfsim's ``tilt = [−α, −β, γ]``. A basic decenter carries on to the
  following surfaces, ``DAR`` returns to the axis before it, ``BEN`` turns the axis once more
  after the surface (fold mirrors), ``REV`` applies the inverse transform after the surface.
* ``ASP`` terms ``A``..``G`` are r⁴..r¹⁶; ``SPS XYP`` coefficients ``C2``… are the
  x^m y^n terms in CODE V's order j = ((m+n)² + m + 3n)/2 + 1 (``C1`` is the conic), over
  ``NRADIUS`` (default 1) like lfsim's ``xy`` terms.
* Glass: a catalog name (``NBK7_SCHOTT``), or a model glass as a code ``NNN.VVV``
  (nd = 1.NNN, Vd = VV.V; any number of digits), or ``nd:vd``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

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

#: CODE V (α, β, γ) → lfsim tilt factors.
TILT_SIGN = (-1.0, -1.0, 1.0)
_ASP = {"A": 4, "B": 6, "C": 8, "D": 10, "E": 12, "F": 14, "G": 16, "H": 18, "J": 20}
_DEC = {"XDE": 0, "YDE": 1, "ZDE": 2, "ADE": 3, "BDE": 4, "CDE": 5}
#: Accepted and without effect on the traced geometry.
_IGNORED = {"LEN", "TIT", "TITLE", "INI", "WTW", "WTF", "VUX", "VLX", "VUY", "VLY", "TEM", "PRE", "GO", "CA",
            "POL", "DER", "SLB", "CCY", "THC", "GLC", "CCX", "PIM", "SCC", "SPH", "RDM", "END", "NAM"}
_TOKEN = re.compile(r"'[^']*'|\"[^\"]*\"|[^\s]+")


def _statements(text: str):
    """(line number, tokens) of every command: ``!`` comments cut, ``&`` continuations joined,
    ``;`` separating commands on one line."""
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        start = i + 1
        buf = ""
        while True:
            line = _cut_comment(lines[i])
            i += 1
            if line.rstrip().endswith("&"):
                buf += line.rstrip()[:-1] + " "
                if i < len(lines):
                    continue
            buf += line
            break
        for part in _split_semicolons(buf):
            toks = _TOKEN.findall(part)
            if toks:
                yield start, toks


def _unquoted(text: str):
    """``(index, char)`` of every character of ``text`` outside '…' and "…" quotes."""
    quote = None
    for k, ch in enumerate(text):
        if quote:
            if ch == quote:
                quote = None
        elif ch in "'\"":
            quote = ch
        else:
            yield k, ch


def _cut_comment(line: str) -> str:
    return next((line[:k] for k, ch in _unquoted(line) if ch == "!"), line)


def _split_semicolons(text: str):
    start = 0
    for k, ch in _unquoted(text):
        if ch == ";":
            yield text[start:k]
            start = k + 1
    yield text[start:]


def xy_index(m: int, n: int) -> int:
    """CODE V's XY-polynomial coefficient number C_j of x^m y^n."""
    p = m + n
    return (p * p + m + 3 * n) // 2 + 1


_XY_OF_J = {xy_index(m, p - m): (m, p - m) for p in range(1, 11) for m in range(p + 1)}


def _model_glass(file, line, tok: str):
    """A CODE V model glass (``517642.0``, ``516800.641700``, ``1.5168:64.17``) as {nd, vd}, or None."""
    if ":" in tok:
        a, _, b = tok.partition(":")
        try:
            return {"nd": float(a), "vd": float(b)}
        except ValueError:
            raise LensFileError(file, line, f"glass {tok!r}: expected nd:vd") from None
    m = re.fullmatch(r"(\d+)(?:\.(\d*))?", tok)
    if not m:
        return None
    digits, frac = m.group(1), m.group(2) or ""
    if len(frac) < 2:
        if "." not in tok and len(digits) == 6:  # a six-digit glass code 517642
            digits, frac = digits[:3], digits[3:]
        else:
            raise LensFileError(file, line, f"glass {tok!r}: a model glass code is NNN.VVV (nd = 1.NNN, Vd = VV.V)")
    return {"nd": float("1." + digits), "vd": float(frac[:2] + "." + frac[2:])}


class _Surf:
    def __init__(self, kind, line, vals):
        self.kind, self.line, self.vals = kind, line, vals
        self.stop = self.refl = False
        self.glass = None
        self.conic = 0.0
        self.asphere: dict[int, float] = {}
        self.xyp = False
        self.xy: dict[tuple[int, int], float] = {}
        self.nradius = None
        self.dec = [0.0] * 6
        self.dtype = None
        self.cir = None
        self.rex = self.rey = None
        self.adx = self.ady = 0.0


def read_seq(path: str | Path, text: str | None = None) -> Imported:
    """Read a CODE V ``.seq`` file into a design table. Raises :class:`LensFileError`."""
    file = str(path)
    if text is None:
        try:
            text = Path(path).read_bytes().decode("utf-8", errors="strict")
        except UnicodeDecodeError:
            text = Path(path).read_bytes().decode("latin-1")
        except OSError as e:
            raise LensFileError(file, None, f"cannot read file ({e.strerror or e})") from None
    if "\x00" in text:
        raise LensFileError(file, None, "not a CODE V sequence file (binary data)")
    check_complete(text, file)
    radius_mode = True
    unit = "M"
    title = ""
    epd = fno = nao = nao_line = None
    yan, xan, yob, xob = [], [], [], []
    wl, ref = [], None
    surfs: list[_Surf] = []
    notes: list[str] = []
    cur: _Surf | None = None

    def need(line, toks, k, what):
        if len(toks) <= k:
            raise LensFileError(file, line, f"{toks[0].upper()}: missing {what}")
        return toks[k]

    def num(line, tok, what):
        return finite(file, line, tok, what)

    for line, toks in _statements(text):
        cmd = toks[0].upper()
        args = toks[1:]

        def surface_only():
            if cur is None:
                raise LensFileError(file, line, f"{cmd} before any surface (SO, S or SI)")
            return cur

        if cmd in ("SO", "S", "SI"):
            if cmd == "SO" and surfs:
                raise LensFileError(file, line, "SO (the object surface) must come first")
            if cmd != "SO" and not surfs:
                raise LensFileError(file, line, f"{cmd} before SO (the object surface)")
            if surfs and surfs[-1].kind == "SI":
                raise LensFileError(file, line, f"{cmd} after SI (the image surface)")
            vals = [num(line, a, f"{cmd} value") for a in args[:2]]
            cur = _Surf(cmd, line, vals + [0.0] * (2 - len(vals)))
            for extra in args[2:]:
                if extra.upper() == "REFL":
                    cur.refl = True
                elif cur.glass is None:
                    cur.glass = extra.strip("'\"")
                else:
                    raise LensFileError(file, line, f"{cmd}: unexpected {extra!r}")
            surfs.append(cur)
        elif cmd in ("RDM",):
            radius_mode = not (args and args[0].upper() in ("N", "NO"))
        elif cmd in ("TIT", "TITLE"):
            title = " ".join(a.strip("'\"") for a in args)
        elif cmd == "DIM":
            if not args or args[0].upper() not in ("M", "MM", "C", "CM", "I", "IN"):
                raise LensFileError(file, line, f"DIM {' '.join(args)}: expected M (mm), C (cm) or I (inches)")
            unit = args[0].upper()
        elif cmd == "WL":
            wl = [num(line, a, "WL") for a in args]
        elif cmd == "REF":
            ref = int(num(line, need(line, toks, 1, "a wavelength number"), "REF"))
        elif cmd == "EPD":
            epd = num(line, need(line, toks, 1, "a diameter"), "EPD")
        elif cmd == "FNO":
            fno = num(line, need(line, toks, 1, "an f-number"), "FNO")
        elif cmd == "NAO":
            nao, nao_line = num(line, need(line, toks, 1, "an NA"), "NAO"), line
        elif cmd in ("YIM", "XIM", "YRI", "XRI"):
            if any(num(line, a, cmd) != 0.0 for a in args):
                raise LensFileError(file, line, f"{cmd}: image-height fields are not supported (YAN angles or "
                                    "YOB object heights)")
        elif cmd in ("YAN", "XAN", "YOB", "XOB"):
            {"YAN": yan, "XAN": xan, "YOB": yob, "XOB": xob}[cmd][:] = [num(line, a, cmd) for a in args]
        elif cmd in ("STO", "STOP"):
            surface_only().stop = True
        elif cmd == "REFL":
            surface_only().refl = True
        elif cmd in ("GLA",):
            surface_only().glass = need(line, toks, 1, "a glass name").strip("'\"")
        elif cmd in ("RDY", "CUY", "THI"):
            s = surface_only()
            v = num(line, need(line, toks, 1, "a value"), cmd)
            if cmd == "THI":
                s.vals[1] = v
            elif (cmd == "RDY") == radius_mode:  # the file's own mode: radius or curvature
                s.vals[0] = v
            else:
                s.vals[0] = 1.0 / v if v else 0.0
        elif cmd in ("ASP", "CON"):
            surface_only()
        elif cmd == "K":
            surface_only().conic = num(line, need(line, toks, 1, "a conic constant"), "K")
        elif cmd in _ASP and cur is not None:
            order = _ASP[cmd]
            v = num(line, need(line, toks, 1, "a coefficient"), cmd)
            if order > 16 and v != 0.0:
                raise LensFileError(file, line, f"{cmd} (r^{order}): asphere terms beyond r^16 (G) are not supported")
            if v != 0.0:
                cur.asphere[order] = v
        elif cmd == "CUF":
            if num(line, need(line, toks, 1, "a value"), "CUF") != 0.0:
                raise LensFileError(file, line, "CUF (a non-zero curvature fraction) is not supported")
        elif cmd == "SPS":
            s = surface_only()
            kind = need(line, toks, 1, "a surface type").upper()
            if kind != "XYP":
                raise LensFileError(file, line, f"SPS {kind}: special surface type not supported (only XYP)")
            s.xyp = True
        elif cmd == "SCO":
            s = surface_only()
            if not s.xyp:
                raise LensFileError(file, line, "SCO without SPS XYP")
            if len(args) < 2 or len(args) % 2:
                raise LensFileError(file, line, "SCO: expected pairs of a coefficient name and a value")
            for name, val in zip(args[::2], args[1::2]):
                key = name.upper()
                v = num(line, val, f"SCO {name}")
                if key in ("K", "C1"):
                    s.conic = v
                elif key in ("NRADIUS", "NRA"):
                    s.nradius = v
                elif re.fullmatch(r"C\d+", key):
                    j = int(key[1:])
                    if j not in _XY_OF_J:
                        if v != 0.0:
                            raise LensFileError(file, line, f"SCO {name}: XY terms beyond total order 10 are not "
                                                "supported")
                        continue
                    if v != 0.0:
                        s.xy[_XY_OF_J[j]] = v
                else:
                    raise LensFileError(file, line, f"SCO {name}: unknown XYP coefficient")
        elif cmd == "NRADIUS":
            s = surface_only()
            s.nradius = num(line, need(line, toks, 1, "a radius"), "NRADIUS")
        elif cmd in _DEC:
            s = surface_only()
            s.dec[_DEC[cmd]] = num(line, need(line, toks, 1, "a value"), cmd)
            s.dtype = s.dtype or "basic"
        elif cmd in ("DAR", "BEN", "REV"):
            surface_only().dtype = cmd
        elif cmd in ("DEC",):
            surface_only().dtype = "basic"
        elif cmd == "CIR":
            s = surface_only()
            quals = [a.upper() for a in args if not _is_number(a)]
            vals = [a for a in args if _is_number(a)]
            if "EDG" in quals:
                continue  # the drawn lens edge, not a clear aperture
            if quals:
                raise LensFileError(file, line, f"CIR {' '.join(quals)}: only clear apertures are supported "
                                    "(no holes or obscurations)")
            s.cir = num(line, vals[0] if vals else need(line, toks, 1, "a radius"), "CIR")
        elif cmd in ("REX", "REY", "ADX", "ADY"):  # rectangle half-widths, aperture offsets
            s = surface_only()
            what = "a half-width" if cmd.startswith("RE") else "an offset"
            setattr(s, cmd.lower(), num(line, need(line, toks, 1, what), cmd))
        elif cmd == "ARO":
            if num(line, need(line, toks, 1, "an angle"), "ARO") != 0.0:
                raise LensFileError(file, line, "ARO (a rotated aperture) is not supported")
        elif cmd in _IGNORED:
            continue
        else:
            raise LensFileError(file, line, f"{cmd}: command not supported by lfsim's CODE V reader")

    if not surfs or surfs[0].kind != "SO":
        raise LensFileError(file, None, "no surfaces (expected SO, S ... SI)")
    if surfs[-1].kind != "SI":
        raise LensFileError(file, None, "no image surface (SI)")
    if len(surfs) < 3:
        raise LensFileError(file, None, "no lens surfaces between SO and SI")

    raw = _assemble(file, surfs, radius_mode, notes)
    name = title or Path(file).stem
    raw = {"name": name, "description": f"Imported from the CODE V file {Path(file).name}", **raw}
    sysd: dict = {}
    at_inf = math.isinf(raw["object"]["distance"])
    if fno is not None:
        sysd["aperture"] = {"type": "fno", "value": fno}
    elif nao is not None:
        if at_inf:
            raise LensFileError(file, nao_line, f"NAO {nao:g}: an object-space NA needs a finite object, and SO "
                                "puts the object at infinity (thickness >= 1e10); give EPD or FNO")
        sysd["aperture"] = {"type": "na", "value": nao}
    elif epd is not None:
        sysd["aperture"] = {"type": "epd", "value": epd}
    if yob and not at_inf:
        fields = {"type": "height", "values": yob}
    else:
        fields = {"type": "angle", "values": yan or [0.0]}
    if xan and any(v != 0.0 for v in xan) or xob and any(v != 0.0 for v in xob):
        notes.append("x field components (XAN/XOB) are not kept: lfsim's [system] field lists y fields only")
    fields["values"] = list(dict.fromkeys(fields["values"]))
    sysd["field"] = fields
    if wl:
        sysd["wavelengths_nm"] = wl
        if ref is not None:
            if not 1 <= ref <= len(wl):
                raise LensFileError(file, None, f"REF {ref}: there are {len(wl)} wavelengths")
            sysd["primary_wavelength_nm"] = wl[ref - 1]
    raw["system"] = sysd
    note_defaults(sysd, notes, "EPD, FNO or NAO", "WL")
    raw = {k: raw[k] for k in ("name", "description", "system", "object", "surfaces")}
    if UNITS_MM[unit] != 1.0:
        notes.append(f"lengths converted from DIM {unit} to millimetres (x {UNITS_MM[unit]:g})")
    return Imported(scale_lengths(raw, UNITS_MM[unit]), notes)


def _is_number(tok: str) -> bool:
    try:
        float(tok)
        return True
    except ValueError:
        return False


def _assemble(file, surfs: list[_Surf], radius_mode: bool, notes) -> dict:
    so = surfs[0]
    obj: dict = {}
    d = so.vals[1]
    if d >= INFINITE_DISTANCE:
        obj["distance"] = math.inf
    elif d > 0:
        obj["distance"] = d
    else:
        raise LensFileError(file, so.line, f"SO thickness {d!r}: the object must lie before the first surface")
    if so.glass:
        obj["material"] = _glass(file, so.line, so.glass)
    medium = obj.get("material", "air")
    out: list[dict] = []
    body = surfs[1:]
    for s in body:
        is_image = s.kind == "SI"
        tab: dict = {"comment": f"{s.kind} at line {s.line}"}
        v = s.vals[0]
        if radius_mode:
            if v != 0.0:
                tab["radius"] = v
            else:
                tab["radius"] = math.inf
        else:
            tab["curvature"] = v
        if s.conic:
            tab["conic"] = s.conic
        if s.asphere:
            tab["asphere"] = {f"A{o}": s.asphere[o] for o in sorted(s.asphere)}
        if s.xy:
            tab["xy"] = {f"x{m}y{n}": c for (m, n), c in sorted(s.xy.items(), key=lambda t: (sum(t[0]), -t[0][0]))}
            if s.nradius is not None:
                tab["norm_radius"] = s.nradius
        thickness = s.vals[1]
        if is_image:
            if thickness and out:
                _last_gap(out)["thickness"] = _last_gap(out).get("thickness", 0.0) + thickness
            thickness = 0.0
        if s.refl:
            if s.glass:
                raise LensFileError(file, s.line, "REFL with a glass: a mirror keeps the medium")
            tab["mirror"] = True
        else:
            after = _glass(file, s.line, s.glass) if s.glass else "air"
            if after == medium:
                tab["dummy"] = True
            else:
                tab["material"] = after
            medium = after
        if s.stop:
            tab["stop"] = True
        if s.cir is not None:
            if s.adx or s.ady:
                tab["aperture"] = {"type": "circular", "radius": s.cir, "decenter": [s.adx, s.ady]}
            else:
                tab["semi_diameter"] = s.cir
        if s.rex is not None or s.rey is not None:
            if s.rex is None or s.rey is None:
                raise LensFileError(file, s.line, "a rectangular aperture needs both REX and REY")
            if "aperture" in tab or "semi_diameter" in tab:
                raise LensFileError(file, s.line, "both CIR and REX/REY on one surface: only one aperture is "
                                    "supported")
            tab["aperture"] = {"type": "rectangular", "half_width": [s.rex, s.rey], "decenter": [s.adx, s.ady]}
        _place(file, s, tab, thickness, out)
    for k, tab in enumerate(out[:-1]):
        if _placement_only(tab):  # a decentred dummy plane only moves the axis: a coordinate break
            out[k] = {"type": "coordinate_break", **{key: tab[key] for key in
                                                     ("decenter", "tilt", "return_axis", "thickness", "comment")
                                                     if key in tab}}
            out[k]["comment"] += " (dummy plane: a coordinate break)"
            if tab.get("return_axis", True) and "return_axis" not in out[k]:
                out[k]["return_axis"] = True
    return {"object": obj, "surfaces": out}


def _placement_only(tab: dict) -> bool:
    flat = tab.get("radius", math.inf) == math.inf and tab.get("curvature", 0.0) == 0.0
    keys = set(tab) - {"comment", "radius", "curvature", "dummy", "decenter", "tilt", "return_axis", "thickness"}
    return bool(tab.get("dummy")) and flat and not keys and ("decenter" in tab or "tilt" in tab)


def _last_gap(out: list[dict]) -> dict:
    return out[-1]


def _place(file, s: _Surf, tab: dict, thickness: float, out: list[dict]) -> None:
    """Append the surface with its decenter (and the coordinate breaks CODE V's types need)."""
    dx, dy, dz, a, b, g = s.dec
    tilt = [TILT_SIGN[0] * a, TILT_SIGN[1] * b, TILT_SIGN[2] * g]
    tilt = [0.0 if t == 0.0 else t for t in tilt]
    has = any(s.dec)
    if not has or s.dtype is None:
        tab["thickness"] = thickness
        out.append(tab)
        return
    if s.dtype == "REV":
        tab["thickness"] = 0.0
        out.append(tab)
        for k in (2, 1, 0):
            if tilt[k]:
                t = [0.0, 0.0, 0.0]
                t[k] = -tilt[k]
                out.append({"type": "coordinate_break", "tilt": t, "thickness": 0.0,
                            "comment": f"REV at line {s.line}: tilt undone"})
        out.append({"type": "coordinate_break", "decenter": [-dx, -dy], "thickness": thickness - dz,
                    "comment": f"REV at line {s.line}: decenter undone"})
        return
    if dz:
        out.append({"type": "coordinate_break", "thickness": dz, "comment": f"ZDE at line {s.line}"})
    if dx or dy:
        tab["decenter"] = [dx, dy]
    if any(tilt):
        tab["tilt"] = tilt
    if s.dtype == "DAR":
        tab["thickness"] = thickness - dz
        out.append(tab)
        return
    tab["return_axis"] = False
    if s.dtype == "BEN":
        tab["thickness"] = 0.0
        out.append(tab)
        out.append({"type": "coordinate_break", "tilt": tilt, "thickness": thickness,
                    "comment": f"BEN at line {s.line}: the axis turned again"})
        return
    tab["thickness"] = thickness
    out.append(tab)


def _glass(file, line, name: str):
    model = _model_glass(file, line, name)
    if model is not None:
        return model
    return material_value(file, line, name)


# --------------------------------------------------------------------- writer
def write_seq(plan, title: str) -> str:
    """CODE V text of an export plan (:func:`lfsim.design.lensfiles.export.plan`)."""
    lines = ["RDM N", "LEN", f"TITLE '{_quote(title)}'"]
    sysd = plan.system
    if sysd.aperture_type == "epd":
        lines.append(f"EPD {fmt(sysd.aperture_value)}")
    elif sysd.aperture_type == "fno":
        lines.append(f"FNO {fmt(sysd.aperture_value)}")
    else:
        lines.append(f"NAO {fmt(sysd.aperture_value)}")
    lines.append("DIM M")
    wl = sysd.wavelengths_nm
    lines.append("WL " + " ".join(fmt(w) for w in wl))
    if sysd.primary_wavelength_nm in wl:
        lines.append(f"REF {wl.index(sysd.primary_wavelength_nm) + 1}")
    key = "YAN" if sysd.field_type == "angle" else "YOB"
    lines.append(f"{key} " + " ".join(fmt(f) for f in sysd.fields))
    obj_d = sysd.object_distance
    so = f"SO 0.0 {'1e11' if math.isinf(obj_d) else fmt(obj_d)}"
    if plan.object_glass is not None:
        so += f" {_glass_token(plan.object_glass, wl, 'the object space')}"
    lines.append(so)
    for e in plan.entries:
        lines += _surface_lines(e, wl)
    lines.append("GO")
    return "\n".join(lines) + "\n"


def _quote(t: str) -> str:
    return t.replace("'", "")


def _glass_token(g, wavelengths, where: str) -> str:
    """CODE V's spelling of a medium: NAME_VENDOR of a vendor catalog that gives the same indices
    at ``wavelengths``, a model glass as nd:vd; ``where`` names the surface in a refusal."""
    if isinstance(g, dict):
        if "n" in g or set(g) != {"nd", "vd"}:
            what = f"n = {fmt(g['n'])}" if "n" in g else ", ".join(f"{k} = {v}" for k, v in g.items())
            raise ValueError(f"{where}: a constant-index medium ({what}) has no CODE V glass form; give the "
                             "design {nd, vd} or a catalog glass, or export with --zmx")
        return f"{fmt(g['nd'])}:{fmt(g['vd'])}"
    from ...optics.glass_catalogs import VENDORS, split_vendor
    from .export import same_index

    name = str(g)
    base, vendor = split_vendor(name)
    bare = re.sub(r"[^A-Za-z0-9]", "", base).upper()
    for v in ([vendor] if vendor else list(VENDORS)):
        cand = f"{bare}_{v}"
        if same_index(cand, name, wavelengths):
            return cand
    raise ValueError(f"{where}: material {name!r} is in no vendor catalog, so CODE V has no name for it "
                     "with the same indices; give the design a vendor catalog glass or a model glass {nd, vd}")


def _surface_lines(e, wl) -> list[str]:
    if e.kind == "paraxial":
        raise ValueError(f"surface {e.name}: an ideal (paraxial) lens has no CODE V sequence form; export "
                         "the design with --zmx (a PARAXIAL surface)")
    head = "SI" if e.image else "S"
    text = f"{head} {fmt(e.curvature)} {fmt(0.0 if e.image else e.thickness)}"
    if e.mirror:
        text += " REFL"
    elif e.glass is not None and not e.image:
        text += f" {_glass_token(e.glass, wl, f'surface {e.name}')}"
    out = [text]
    if e.stop:
        out.append("  STO")
    if e.xy:
        out.append("  SPS XYP")
        out.append(f"  SCO K {fmt(e.conic)}")
        if e.norm_radius != 1.0:
            out.append(f"  SCO NRADIUS {fmt(e.norm_radius)}")
        for (m, n), c in sorted(e.xy.items(), key=lambda t: xy_index(*t[0])):
            out.append(f"  SCO C{xy_index(m, n)} {fmt(c)}")
        if e.asphere:
            raise ValueError(f"surface {e.name}: CODE V's XYP surface has no separate even-asphere terms")
    elif e.asphere:
        out.append("  ASP")
        out.append(f"  K {fmt(e.conic)}")
        letters = {v: k for k, v in _ASP.items()}
        for o in sorted(e.asphere):
            out.append(f"  {letters[o]} {fmt(e.asphere[o])}")
    elif e.conic:
        out.append("  CON")
        out.append(f"  K {fmt(e.conic)}")
    if e.decenter is not None:
        dx, dy, dz, tx, ty, tz = e.decenter
        for key, v in (("XDE", dx), ("YDE", dy), ("ZDE", dz), ("ADE", TILT_SIGN[0] * tx),
                       ("BDE", TILT_SIGN[1] * ty), ("CDE", TILT_SIGN[2] * tz)):
            if v:
                out.append(f"  {key} {fmt(v)}")
        if e.dar:
            out.append("  DAR")
    ap = e.aperture
    if ap is not None:
        if ap.kind == "circular":
            out.append(f"  CIR {fmt(ap.radius)}")
        else:
            out.append(f"  REX {fmt(ap.half_width[0])}")
            out.append(f"  REY {fmt(ap.half_width[1])}")
        if ap.decenter[0]:
            out.append(f"  ADX {fmt(ap.decenter[0])}")
        if ap.decenter[1]:
            out.append(f"  ADY {fmt(ap.decenter[1])}")
    return out
