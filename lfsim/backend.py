"""The one place where lfsim chooses its Dr.Jit / Mitsuba back end.

Everything that needs Dr.Jit array types asks :func:`types` for them; nothing
else in lfsim imports ``drjit.llvm`` or ``drjit.cuda`` directly. Choices:

* **device**: CUDA when a GPU is present, else LLVM (CPU). Override with the
  environment variable ``LFSIM_DEVICE=cpu|cuda`` or :func:`configure`.
* **precision**: ``"float64"`` (default for design and analysis) or
  ``"float32"`` (allowed for rendering and speed).
* **threads**: the LLVM back end's worker count (``LFSIM_THREADS`` or
  :func:`configure`); default: all cores.
* **vector width**: the SIMD width LLVM compiles kernels for
  (``LFSIM_VECTOR_WIDTH`` = 4, 8 or 16; default the CPU's, 8 on AVX2).
  Narrower kernels compile faster and run slower (AVX2, 1e6 rays: width 4
  compiles a large kernel ~2.6× faster and traces ~25 % slower than 8).
  Launches of a few dozen lanes use :func:`compact_kernels` whatever the
  setting.

Dr.Jit JIT-compiles kernels through libLLVM. Debian 12's libLLVM 15 makes the
process abort natively (uncatchable) on ``fminimum``/``fmaximum`` intrinsics, so
:func:`init` checks the loaded libLLVM version first and raises
:class:`BackendError` with the fix instead.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

#: Oldest libLLVM major version known to compile every kernel lfsim emits.
MIN_LLVM_MAJOR = 16

_state = {"device": None, "threads": None, "initialized": False}

#: LLVM vector width of kernels launched inside :func:`compact_kernels` (first-order
#: linearizations, frames, a few chief rays: launches of tens of lanes).
COMPACT_VECTOR_WIDTH = 4


class BackendError(RuntimeError):
    """The Dr.Jit back end cannot be used; the message says how to fix it."""


def _llvm_fix_hint() -> str:
    return (
        "install a newer libLLVM (Debian/Ubuntu: 'apt-get install libllvm19') "
        "or point DRJIT_LIBLLVM_PATH at libLLVM.so.16 or newer"
    )


def check_llvm() -> tuple[int, int, int]:
    """Return the libLLVM version Dr.Jit loaded; raise if it is unusable.

    Raises
    ------
    BackendError
        When no libLLVM could be loaded or its major version is below
        :data:`MIN_LLVM_MAJOR`.
    """
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(
            "Dr.Jit could not load libLLVM (needed for the CPU back end): " + _llvm_fix_hint()
        )
    version = tuple(int(v) for v in dr.detail.llvm_version())
    if version[0] < MIN_LLVM_MAJOR:
        raise BackendError(
            f"Dr.Jit loaded libLLVM {'.'.join(map(str, version))}, which aborts on "
            f"kernels lfsim compiles (needs >= {MIN_LLVM_MAJOR}): " + _llvm_fix_hint()
        )
    return version


def configure(device: str | None = None, threads: int | None = None) -> None:
    """Choose the device (``"cpu"``, ``"cuda"`` or ``None`` = auto) and thread count.

    Must be called before the first traced kernel to take full effect.
    """
    if device not in (None, "cpu", "cuda"):
        raise BackendError(f"unknown device {device!r}: allowed 'cpu', 'cuda'")
    _state["device"] = device
    _state["threads"] = threads
    _state["initialized"] = False
    init()


def init() -> str:
    """Initialise the back end once (idempotent) and return ``"cpu"`` or ``"cuda"``."""
    if _state["initialized"]:
        return _state["device"]
    import drjit as dr

    device = _state["device"] or os.environ.get("LFSIM_DEVICE") or None
    if device not in (None, "cpu", "cuda"):
        raise BackendError(f"LFSIM_DEVICE={device!r} is not allowed: use 'cpu' or 'cuda'")
    if device is None:
        device = "cuda" if dr.has_backend(dr.JitBackend.CUDA) else "cpu"
    if device == "cuda" and not dr.has_backend(dr.JitBackend.CUDA):
        raise BackendError("LFSIM_DEVICE=cuda but Dr.Jit finds no CUDA device/driver")
    if device == "cpu":
        check_llvm()
        threads = _state["threads"] or os.environ.get("LFSIM_THREADS")
        if threads:
            try:
                n = int(threads)
            except ValueError:
                raise BackendError(f"LFSIM_THREADS={threads!r} is not an integer") from None
            if n < 1:
                raise BackendError(f"LFSIM_THREADS={n} must be >= 1")
            dr.set_thread_count(n)
    _state["device"] = device
    _state["initialized"] = True
    if device == "cpu":
        width = os.environ.get("LFSIM_VECTOR_WIDTH")
        if width:
            try:
                w = int(width)
            except ValueError:
                w = 0
            if w not in (4, 8, 16):
                _state["initialized"] = False
                raise BackendError(f"LFSIM_VECTOR_WIDTH={width!r} is not allowed: use 4, 8 or 16")
            t = _llvm_target()
            if t is not None:
                t.set_width(w)
    return device


@dataclass(frozen=True)
class Precision:
    name: str
    np_dtype: type


PRECISIONS = {"float64": Precision("float64", np.float64), "float32": Precision("float32", np.float32)}


def check_precision(precision: str) -> Precision:
    try:
        return PRECISIONS[precision]
    except KeyError:
        raise ValueError(
            f"precision {precision!r} is not allowed: use 'float64' or 'float32'"
        ) from None


_types_cache: dict[tuple[str, str], SimpleNamespace] = {}


def types(precision: str = "float64") -> SimpleNamespace:
    """Dr.Jit AD array types for the active device and the given precision.

    Returns a namespace with ``Float``, ``UInt32``, ``Int32``, ``Bool``,
    ``Array3`` (3-vectors), ``Matrix3`` and ``np_dtype``.
    """
    prec = check_precision(precision)
    device = init()
    key = (device, prec.name)
    if key not in _types_cache:
        import drjit as dr

        mod = dr.cuda.ad if device == "cuda" else dr.llvm.ad
        suffix = "f64" if prec.name == "float64" else "f"
        _types_cache[key] = SimpleNamespace(
            Float=getattr(mod, "Float64" if suffix == "f64" else "Float"),
            UInt32=mod.UInt32,
            Int32=mod.Int32,
            Int64=mod.Int64,
            Bool=mod.Bool,
            Array3=getattr(mod, "Array3" + suffix),
            Matrix3=getattr(mod, "Matrix3" + suffix),
            np_dtype=prec.np_dtype,
            precision=prec.name,
            device=device,
        )
    return _types_cache[key]


def _aligned(a) -> np.ndarray:
    """A contiguous copy of ``a`` on a 64-byte boundary.

    The copy kernel of :func:`from_numpy` reads the numpy buffer itself, and
    its IR states the buffer's alignment: a fixed alignment keeps that one
    small kernel from compiling again for each allocation."""
    a = np.asarray(a)
    if a.ctypes.data % 64 == 0 and a.flags.c_contiguous:
        return a
    buf = np.empty(a.nbytes + 64, dtype=np.uint8)
    off = (-buf.ctypes.data) % 64
    out = buf[off:off + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


def from_numpy(Type, *arrays):
    """Dr.Jit arrays of ``Type`` holding copies of numpy arrays (one kernel).

    Dr.Jit maps numpy buffers without copying (``dr.copy`` keeps the
    mapping), and a kernel that reads such a buffer has the buffer's
    alignment baked into its code, so the same trace would recompile whenever
    numpy happens to allocate differently. Multiplying by an opaque 1 (exact)
    and evaluating writes the values into Dr.Jit's own aligned memory, which
    keeps kernels cache-stable. Returns one array, or a tuple for several.
    """
    import drjit as dr

    one = dr.opaque(Type, 1)
    out = tuple(Type(_aligned(a)) * one for a in arrays)
    dr.eval(*out)
    return out[0] if len(out) == 1 else out


class _LLVMTarget:
    """Dr.Jit's LLVM code-generation target (CPU, features, vector width).

    Dr.Jit compiles every kernel for one SIMD width (8 lanes on AVX2, 16 on
    AVX-512). LLVM's compile time grows faster than linearly with the IR a
    kernel holds, and a float64 kernel at width 8 is twice the IR of the
    machine's natural width, so a large kernel of a few dozen lanes (a
    first-order linearization) spends seconds in register allocation for
    microseconds of work. drjit-core exports ``jit_llvm_set_target`` (the
    target is part of every kernel's cache key, so kernels of each width are
    cached side by side); it is not bound in Python, so it is reached through
    ctypes. Where the symbol is missing, width changes are skipped.
    """

    def __init__(self):
        self.lib = None
        try:
            import drjit as dr

            lib = ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))
            get_cpu, get_feat = lib._Z19jit_llvm_target_cpuv, lib._Z24jit_llvm_target_featuresv
            get_vw, set_target = lib._Z21jit_llvm_vector_widthv, lib._Z19jit_llvm_set_targetPKcS0_j
        except (OSError, AttributeError):
            return
        get_cpu.restype = get_feat.restype = ctypes.c_char_p
        get_vw.restype = ctypes.c_uint32
        set_target.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
        self.lib = lib
        self._get_cpu, self._get_feat, self._get_vw, self._set = get_cpu, get_feat, get_vw, set_target

    def width(self) -> int | None:
        return int(self._get_vw()) if self.lib is not None else None

    def set_width(self, width: int) -> None:
        if self.lib is not None:
            self._set(self._get_cpu(), self._get_feat(), int(width))


_target: _LLVMTarget | None = None


def _llvm_target() -> _LLVMTarget | None:
    global _target
    if init() != "cpu":
        return None
    if _target is None:
        _target = _LLVMTarget()
    return _target


def vector_width() -> int | None:
    """The LLVM vector width kernels compile at now (None: not the CPU back end)."""
    t = _llvm_target()
    return t.width() if t is not None else None


@contextlib.contextmanager
def compact_kernels(width: int | None = None):
    """Compile the kernels launched inside at a narrow LLVM vector width.

    For launches of a few dozen lanes whose kernels are large (a trace of
    every surface, with forward-mode derivatives), and for register-heavy
    forward-mode kernels that spill at the full width (the optimizer's
    Jacobian: 23 s to compile and 1.9 s per launch at 4, several times both
    at 8). Their compile time is what a user waits for, and at width 4 LLVM compiles them 3–5× faster
    than at the AVX2 width of 8 (measured on the 19-surface InI design:
    a 12.5k-op first-order kernel 25 s → 5.4 s). Only widths that Dr.Jit
    itself selects on some CPU (4, 8, 16) are used: at widths 1 and 2 Dr.Jit
    1.5 refuses packet gathers and some kernels crash. Each lane's arithmetic is the same IEEE
    operations at any width, so results are bit for bit the same. Every
    array that must be computed inside has to be evaluated before the block
    ends (kernels compile when evaluated). A no-op on CUDA.
    """
    t = _llvm_target()
    if t is None or t.lib is None:
        yield
        return
    old = t.width()
    new = int(width or COMPACT_VECTOR_WIDTH)
    if new == old:
        yield
        return
    import drjit as dr

    dr.eval()  # what was queued before belongs to the wide kernels
    t.set_width(new)
    try:
        yield
    finally:
        dr.eval()
        t.set_width(old)


def to_numpy(*values, dtype=None):
    """Evaluate Dr.Jit arrays together (one kernel), then convert each to numpy.

    Reading lazily computed outputs one by one makes Dr.Jit compile and run
    one kernel per read, each re-tracing everything the output depends on.
    Vectors (``Array3``) come back as (N, 3); scalars as (N,). A single value
    is returned alone, several as a tuple.
    """
    import drjit as dr

    dr.eval(*values)
    out = []
    for v in values:
        if dr.depth_v(v) > 1 and not dr.is_tensor_v(v):
            comps = [np.asarray(v[i]) for i in range(len(v))]
            n = max(c.size for c in comps)
            a = np.stack([np.broadcast_to(c, (n,)) for c in comps], axis=1)
        else:
            a = np.asarray(v)
        out.append(a.astype(dtype) if dtype is not None else a)
    return out[0] if len(out) == 1 else tuple(out)


def mitsuba():
    """The ``mitsuba`` module with lfsim's variant set (float32 RGB, differentiable)."""
    import mitsuba as mi

    variant = mitsuba_variant()
    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


_PLUGINS: set[tuple[str, str, str]] = set()


def register_plugin(kind: str, name: str, make_class):
    """Register a Python Mitsuba plugin once per variant (``kind``: "sensor", "bsdf",
    "integrator", ...; ``make_class(mi)`` defines its class); returns the mitsuba module."""
    mi = mitsuba()
    key = (mi.variant(), kind, name)
    if key not in _PLUGINS:
        cls = make_class(mi)
        getattr(mi, f"register_{kind}")(name, lambda props: cls(props))
        _PLUGINS.add(key)
    return mi


def mitsuba_variant(spectral: bool = False) -> str:
    """Mitsuba variant matching the Dr.Jit back end (always differentiable)."""
    device = init()
    return f"{'cuda' if device == 'cuda' else 'llvm'}_ad_{'spectral' if spectral else 'rgb'}"
