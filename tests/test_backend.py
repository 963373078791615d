"""The libLLVM lookup and the variant decision (never an abort: scalar fallback + warning)."""
from __future__ import annotations

from pathlib import Path

from rendering.backend import (
    MIN_LLVM_MAJOR,
    SCALAR_VARIANT,
    find_libllvm,
    llvm_major_version,
    resolve_variant,
    select_variant,
)


def test_bad_explicit_path_falls_back_to_scalar_with_warning(tmp_path: Path) -> None:
    bogus = tmp_path / "libLLVM-99.so"
    bogus.write_bytes(b"not a shared library")
    choice = find_libllvm(env={"DRJIT_LIBLLVM_PATH": str(bogus)})
    assert choice.path is None and str(bogus) in choice.reason
    variant, warning = resolve_variant("llvm_ad_rgb", choice)
    assert variant == SCALAR_VARIANT
    assert warning is not None and "\n" not in warning and str(bogus) in warning


def test_missing_explicit_path_is_not_replaced_by_another_library() -> None:
    choice = find_libllvm(env={"DRJIT_LIBLLVM_PATH": "/nonexistent/libLLVM.so"})
    assert choice.path is None
    assert resolve_variant("llvm_ad_rgb", choice)[0] == SCALAR_VARIANT


def test_no_library_found_falls_back_to_scalar(tmp_path: Path) -> None:
    choice = find_libllvm(env={}, globs=(str(tmp_path / "libLLVM-*.so"),))
    assert choice.path is None and "libllvm19" in choice.reason
    variant, warning = resolve_variant("llvm_ad_rgb", choice)
    assert variant == SCALAR_VARIANT and warning and "scalar_rgb" in warning


def test_unloadable_library_has_no_version(tmp_path: Path) -> None:
    fake = tmp_path / "libLLVM-20.so"
    fake.write_bytes(b"\x7fELF garbage")
    assert llvm_major_version(str(fake)) is None
    assert llvm_major_version(str(tmp_path / "absent.so")) is None


def test_old_llvm_is_rejected_when_present() -> None:
    old = [p for p in Path("/usr/lib").glob("*-linux-gnu/libLLVM-1[45].so")]
    for path in old:  # Debian's LLVM 14/15, where the machine has them
        major = llvm_major_version(str(path))
        assert major is not None and major < MIN_LLVM_MAJOR
        assert find_libllvm(env={"DRJIT_LIBLLVM_PATH": str(path)}).path is None


def test_scalar_request_needs_no_llvm() -> None:
    assert resolve_variant("scalar_rgb", None) == ("scalar_rgb", None)


def test_selected_variant_is_stable(mi) -> None:
    assert select_variant() == mi.variant()
    assert select_variant("scalar_rgb") == mi.variant()  # first choice wins for the process
