"""The one place where lfsim chooses its Dr.Jit / Mitsuba back end.

Everything that needs Dr.Jit array types asks :func:`types` for them; nothing
else in lfsim imports ``drjit.llvm`` or ``drjit.cuda`` directly. Choices:

* **device**: CUDA when a GPU is present, else LLVM (CPU). Override with the
  environment variable ``LFSIM_DEVICE=cpu|cuda`` or :func:`configure`.
* **precision**: ``"float64"`` (default for design and analysis) or
  ``"float32"`` (allowed for rendering and speed).
* **threads**: the LLVM back end's worker count (``LFSIM_THREADS`` or
  :func:`configure`); default: all cores.

Dr.Jit JIT-compiles kernels through libLLVM. Debian 12's libLLVM 15 makes the
process abort natively (uncatchable) on ``fminimum``/``fmaximum`` intrinsics, so
:func:`init` checks the loaded libLLVM version first and raises
:class:`BackendError` with the fix instead.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

#: Oldest libLLVM major version known to compile every kernel lfsim emits.
MIN_LLVM_MAJOR = 16

_state = {"device": None, "threads": None, "initialized": False}


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
            Bool=mod.Bool,
            Array3=getattr(mod, "Array3" + suffix),
            Matrix3=getattr(mod, "Matrix3" + suffix),
            np_dtype=prec.np_dtype,
            precision=prec.name,
            device=device,
        )
    return _types_cache[key]


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
    out = tuple(Type(np.ascontiguousarray(a)) * one for a in arrays)
    dr.eval(*out)
    return out[0] if len(out) == 1 else out


def mitsuba_variant(spectral: bool = False) -> str:
    """Mitsuba variant matching the Dr.Jit back end (always differentiable)."""
    device = init()
    return f"{'cuda' if device == 'cuda' else 'llvm'}_ad_{'spectral' if spectral else 'rgb'}"
