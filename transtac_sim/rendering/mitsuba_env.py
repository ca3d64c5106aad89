"""Choosing Mitsuba's variant, and finding a libLLVM that its CPU (``llvm_*``) variants can use.

``select_variant(None)`` picks ``cuda_ad_rgb`` when Dr.Jit sees a CUDA GPU, else ``llvm_ad_rgb``; the
environment variable ``TRANSTAC_SIM_VARIANT`` overrides the automatic choice. Mitsuba 3.9's LLVM
variants crash with Debian's default LLVM 15 ("Cannot select fminimum"); when ``DRJIT_LIBLLVM_PATH`` is
unset this module points Dr.Jit at a libLLVM 19, 18, 20 or 17 before the LLVM backend starts, and raises
``RendererUnavailable`` saying what to install when there is none.
"""

from __future__ import annotations

import glob
import os

LLVM_VERSIONS = (19, 18, 20, 17)
_LIB_DIRS = ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib64", "/usr/lib")


class RendererUnavailable(RuntimeError):
    """No usable Mitsuba variant on this machine; the message says what to install."""


def find_libllvm(versions=LLVM_VERSIONS, lib_dirs=_LIB_DIRS) -> str | None:
    """Path of the first libLLVM of ``versions`` (in that order of preference) found, or None."""
    for v in versions:
        for d in lib_dirs:
            for pattern in (f"{d}/libLLVM.so.{v}*", f"{d}/libLLVM-{v}.so*", f"/usr/lib/llvm-{v}/lib/libLLVM*.so*"):
                hits = sorted(glob.glob(pattern))
                if hits:
                    return hits[0]
    return None


def _ensure_libllvm() -> None:
    if os.environ.get("DRJIT_LIBLLVM_PATH"):
        return
    lib = find_libllvm()
    if lib is None:
        raise RendererUnavailable(
            "Mitsuba's CPU variants need libLLVM 17-20 (Debian's default LLVM 15 crashes Mitsuba 3.9 with "
            "'Cannot select fminimum'): run `apt-get install libllvm19`, or set DRJIT_LIBLLVM_PATH")
    os.environ["DRJIT_LIBLLVM_PATH"] = lib


def has_cuda() -> bool:
    """True when Dr.Jit can use a CUDA GPU here."""
    import drjit as dr

    try:
        return bool(dr.has_backend(dr.JitBackend.CUDA))
    except Exception:
        return False


def select_variant(variant: str | None = None):
    """Set Mitsuba's variant (``None``: automatic, see the module doc) and return the ``mitsuba`` module."""
    variant = variant or os.environ.get("TRANSTAC_SIM_VARIANT")
    if variant is None:
        if not os.environ.get("DRJIT_LIBLLVM_PATH") and find_libllvm():  # before Dr.Jit's LLVM backend starts
            os.environ["DRJIT_LIBLLVM_PATH"] = find_libllvm()
        variant = "cuda_ad_rgb" if has_cuda() else "llvm_ad_rgb"
    if variant.startswith("llvm"):
        _ensure_libllvm()
    import mitsuba as mi

    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as e:
            raise RendererUnavailable(f"Mitsuba variant {variant!r} is not usable here: {e}") from None
    return mi
