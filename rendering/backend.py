"""Mitsuba variant selection and the libLLVM lookup that must run before it.

mitsuba 3.9.1 / drjit 1.5 JIT-compile through libLLVM and need LLVM >= 16: with Debian's LLVM 14/15
the process aborts inside the compiler ("Cannot select ... fminimum"), which no Python code can catch.
So the library is checked here, before any ``llvm_*`` variant is set: ``DRJIT_LIBLLVM_PATH`` if the
user set it, else the usual install locations. With no usable library we fall back to
``scalar_rgb`` with a one-line warning.
"""
from __future__ import annotations

import ctypes
import glob
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

MIN_LLVM_MAJOR = 16
LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"

# Newest first: the first usable match wins.
DEFAULT_LLVM_GLOBS: tuple[str, ...] = (
    "/usr/lib/*-linux-gnu/libLLVM-[0-9][0-9].so",
    "/usr/lib/*-linux-gnu/libLLVM.so.[0-9][0-9]*",
    "/usr/lib/*-linux-gnu/libLLVM-[0-9][0-9].so.1",
    "/usr/lib/llvm-[0-9][0-9]/lib/libLLVM.so",
    "/usr/lib/llvm-[0-9][0-9]/lib/libLLVM-[0-9][0-9].so",
    "/usr/lib64/libLLVM.so",
    "/usr/lib64/libLLVM-[0-9][0-9].so",
    "/usr/local/lib/libLLVM.so",
    "/opt/homebrew/opt/llvm/lib/libLLVM.dylib",
    "/usr/local/opt/llvm/lib/libLLVM.dylib",
)


class BackendWarning(UserWarning):
    """Raised (as a warning) when Mitsuba has to fall back to the slow scalar variant."""


@dataclass(frozen=True)
class LLVMChoice:
    """Result of the lookup: a usable library path (or None) and why."""

    path: str | None
    major: int | None
    reason: str


def llvm_major_version(path: str) -> int | None:
    """Major version of the libLLVM at ``path``, or None if it cannot be loaded.

    ``LLVMGetVersion`` exists from LLVM 16 on, so a library that loads but lacks it is older
    than 16 (reported as 15, "too old").
    """
    if not os.path.isfile(path):
        return None
    try:
        lib = ctypes.CDLL(path, mode=ctypes.RTLD_LOCAL)
    except OSError:
        return None
    try:
        get_version = lib.LLVMGetVersion
    except AttributeError:
        return MIN_LLVM_MAJOR - 1
    major, minor, patch = ctypes.c_uint(), ctypes.c_uint(), ctypes.c_uint()
    get_version.argtypes = [ctypes.POINTER(ctypes.c_uint)] * 3
    get_version.restype = None
    get_version(ctypes.byref(major), ctypes.byref(minor), ctypes.byref(patch))
    return int(major.value)


def _candidates(globs: Sequence[str]) -> list[str]:
    found: list[str] = []
    for pattern in globs:
        # Sort by embedded version, newest first, so libLLVM-19 beats libLLVM-16.
        for path in sorted(glob.glob(pattern), key=_version_key, reverse=True):
            real = os.path.realpath(path)
            if real not in (os.path.realpath(p) for p in found):
                found.append(path)
    return found


def _version_key(path: str) -> tuple[int, str]:
    digits = "".join(c if c.isdigit() else " " for c in os.path.basename(path)).split()
    return (int(digits[0]) if digits else 0, path)


def find_libllvm(
    env: Mapping[str, str] | None = None, globs: Sequence[str] = DEFAULT_LLVM_GLOBS
) -> LLVMChoice:
    """Find a libLLVM >= 16 for Dr.Jit.

    An explicit ``DRJIT_LIBLLVM_PATH`` is honoured and never second-guessed: if it is unusable
    the answer is "none" (scalar fallback), not a silent switch to another library.
    """
    env = os.environ if env is None else env
    explicit = env.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        major = llvm_major_version(explicit)
        if major is None:
            return LLVMChoice(None, None, f"DRJIT_LIBLLVM_PATH={explicit} cannot be loaded")
        if major < MIN_LLVM_MAJOR:
            return LLVMChoice(None, major, f"DRJIT_LIBLLVM_PATH={explicit} is LLVM < {MIN_LLVM_MAJOR}")
        return LLVMChoice(explicit, major, "DRJIT_LIBLLVM_PATH")
    for path in _candidates(globs):
        major = llvm_major_version(path)
        if major is not None and major >= MIN_LLVM_MAJOR:
            return LLVMChoice(path, major, "found on the system")
    return LLVMChoice(None, None, f"no libLLVM >= {MIN_LLVM_MAJOR} found (apt-get install libllvm19)")


def resolve_variant(wanted: str, choice: LLVMChoice | None = None) -> tuple[str, str | None]:
    """Decide the variant for ``wanted`` given an LLVM lookup result (pure; no Mitsuba import).

    Returns ``(variant, warning)``: an ``llvm_*`` request without a usable libLLVM becomes
    ``scalar_rgb`` with a one-line warning; anything else is returned unchanged.
    """
    if not wanted.startswith("llvm_"):
        return wanted, None
    choice = find_libllvm() if choice is None else choice
    if choice.path is None:
        return SCALAR_VARIANT, f"Mitsuba falls back to {SCALAR_VARIANT} (slow): {choice.reason}"
    return wanted, None


_selected: str | None = None


def select_variant(prefer: str | None = None) -> str:
    """Set and return the Mitsuba variant for this process; the one place that decides it.

    ``prefer`` (or env ``DENOISER_MI_VARIANT``) may force a variant, e.g. ``scalar_rgb``. An
    ``llvm_*`` variant is only used when a libLLVM >= 16 was found; otherwise the scalar variant is
    used with a one-line :class:`BackendWarning`. Idempotent: later calls return the first choice.
    """
    global _selected
    if _selected is not None:
        return _selected
    wanted = prefer or os.environ.get("DENOISER_MI_VARIANT") or LLVM_VARIANT
    choice = find_libllvm() if wanted.startswith("llvm_") else None
    variant, warning = resolve_variant(wanted, choice)
    if warning:
        warnings.warn(warning, BackendWarning, stacklevel=2)
    elif choice is not None and choice.path is not None:
        os.environ["DRJIT_LIBLLVM_PATH"] = choice.path  # read by Dr.Jit when the variant is set
    import mitsuba as mi  # imported only now: DRJIT_LIBLLVM_PATH must be set first

    mi.set_variant(variant)
    _selected = variant
    return variant
