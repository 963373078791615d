"""Pack the wheels a lent GPU machine lacks, slimmed to fit the 64 MiB it may be sent with the tree.

    python -m benchmarks.gpu_pack WHEEL... [--out shared/gpu/wheels]

Copies each wheel into ``--out``; a Mitsuba wheel loses the variants training data does not need
(every variant but ``scalar_rgb``, ``llvm_ad_rgb`` and ``cuda_ad_rgb``) and the spectral upsampling
table (``data/srgb.coeff``, read by spectral variants only). Every copy is recompressed with LZMA
(a zip still, which ``python -m zipfile -e`` unpacks; pip's wheels use deflate): Mitsuba 3.9.1 for
Python 3.12 59.7 -> 24.8 MiB, Dr.Jit 4.7 -> 3.3, OpenEXR 1.7 -> 1.3 (measured; the same cut of the
Python 3.11 package renders every scene family with the LLVM variant). ``benchmarks/gpu_train.sh``
unpacks what it finds there. The wheels themselves come from PyPI on a machine with network, for
the GPU machine's Python (it has numpy, safetensors and tqdm already)::

    pip download --no-deps --only-binary=:all: --python-version 3.12 --platform manylinux_2_28_x86_64 \\
        -d wheels mitsuba==3.9.1 drjit==1.5.0 OpenEXR
"""
from __future__ import annotations

import argparse
import re
import sys
import zipfile
from pathlib import Path

KEEP_VARIANTS = ("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")
_VARIANT = re.compile(r"^mitsuba/((?:scalar|llvm_ad|cuda_ad)_[a-z_]+)\.cpython")
DROPPED_FILES = ("mitsuba/data/srgb.coeff",)


def kept(name: str) -> bool:
    """True for a file of a Mitsuba wheel that the training data's renders need."""
    match = _VARIANT.match(name)
    return not (match and match.group(1) not in KEEP_VARIANTS) and name not in DROPPED_FILES


def pack(wheel: Path, out: Path) -> Path:
    """Copy ``wheel`` into ``out``, LZMA-compressed (and slimmed when it is Mitsuba's); return the copy's path."""
    out.mkdir(parents=True, exist_ok=True)
    target = out / wheel.name
    with zipfile.ZipFile(wheel) as source, zipfile.ZipFile(target, "w", zipfile.ZIP_LZMA) as dest:
        slim = wheel.name.startswith("mitsuba-")
        for item in source.infolist():
            if not slim or kept(item.filename):
                copy = zipfile.ZipInfo(item.filename, item.date_time)
                copy.external_attr, copy.compress_type = item.external_attr, zipfile.ZIP_LZMA
                dest.writestr(copy, source.read(item))
    return target


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("wheels", nargs="+", type=Path)
    parser.add_argument("--out", type=Path, default=Path("shared/gpu/wheels"))
    args = parser.parse_args(argv)
    total = 0
    for wheel in args.wheels:
        target = pack(wheel, args.out)
        total += target.stat().st_size
        print(f"{target}: {wheel.stat().st_size / 2**20:.1f} -> {target.stat().st_size / 2**20:.1f} MiB")
    print(f"{args.out}: {total / 2**20:.1f} MiB in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
