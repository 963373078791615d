#!/usr/bin/env bash
# Train a recipe on a lent GPU machine for a given number of minutes (docs/training.md, "On a GPU").
#
#   benchmarks/gpu_train.sh RECIPE MINUTES [RUN_DIR]
#
# The machine has Python and a CUDA build of torch but maybe not the project's other packages, and
# no network. What it lacks comes with the working tree as carried files:
#   GPU_WHEELS  folder of wheels to install first (default shared/gpu/wheels): mitsuba and drjit to
#               render the recipe's data there, and OpenEXR, safetensors, tqdm when missing;
#   GPU_DATA    the recipe's datasets as a folder or a .tar.gz of them (default shared/gpu/data):
#               used instead of rendering when present.
# RUN_DIR defaults to $OUT/RECIPE (the device tool brings back what is under $OUT), else
# gpu-runs/RECIPE. The datasets go to DATA_ROOT (default /tmp/gpu-data), never under RUN_DIR.
# MINUTES bounds the whole command (rendering included); the run resumes where it stopped when the
# same command runs again on the same machine, or with `train --recipe RECIPE --out RUN_DIR` anywhere.
#
# DRY_RUN=1: check the environment and print the recipe's plan; render and train nothing (what CI runs
# on a CPU). DEVICE (default cuda) is passed to train --device.
set -euo pipefail

if [ $# -lt 2 ]; then
  echo "usage: $0 RECIPE MINUTES [RUN_DIR]" >&2
  exit 2
fi
RECIPE=$1
MINUTES=$2
ROOT=$(cd "$(dirname "$0")/.." && pwd)
RUN_DIR=${3:-${OUT:+$OUT/$(basename "$RECIPE" .toml)}}
RUN_DIR=${RUN_DIR:-gpu-runs/$(basename "$RECIPE" .toml)}
PY=${PYTHON:-python3}
DEVICE=${DEVICE:-cuda}
DATA_ROOT=${DATA_ROOT:-/tmp/gpu-data}
GPU_WHEELS=${GPU_WHEELS:-$ROOT/shared/gpu/wheels}
GPU_DATA=${GPU_DATA:-$ROOT/shared/gpu/data}
SITE=${SITE:-/tmp/gpu-site}  # the carried wheels, unpacked (a wheel is a zip of its site-packages files)
export PYTHONPATH="$ROOT:$SITE${PYTHONPATH:+:$PYTHONPATH}"

say() { echo "gpu_train: $*"; }

case $MINUTES in
  ''|*[!0-9.]*) echo "gpu_train: MINUTES must be a number, got '$MINUTES'" >&2; exit 2 ;;
esac

say "machine: $(nproc) cores, $("$PY" --version 2>&1)"
"$PY" - "$DEVICE" "${DRY_RUN:-0}" <<'EOF'
import sys
import torch
cuda = torch.cuda.is_available()
name = torch.cuda.get_device_name(0) if cuda else "none"
print(f"gpu_train: torch {torch.__version__}, CUDA available: {cuda}, GPU: {name}")
if sys.argv[1].startswith("cuda") and not cuda and sys.argv[2] != "1":
    sys.exit("gpu_train: --device cuda asked, but torch sees no CUDA device (DEVICE=cpu to run on the CPU)")
EOF

if [ -d "$GPU_WHEELS" ] && ls "$GPU_WHEELS"/*.whl >/dev/null 2>&1; then
  if [ "${DRY_RUN:-0}" = 1 ]; then
    say "would install $(ls "$GPU_WHEELS"/*.whl | wc -l) wheel(s) from $GPU_WHEELS"
  else
    say "unpacking the carried wheels of $GPU_WHEELS into $SITE"
    mkdir -p "$SITE"
    for wheel in "$GPU_WHEELS"/*.whl; do "$PY" -m zipfile -e "$wheel" "$SITE"; done
  fi
fi

missing=$("$PY" - <<'EOF'
import importlib.util
need = ["numpy", "safetensors", "OpenEXR", "tqdm"]
print(" ".join(n for n in need if importlib.util.find_spec(n) is None))
EOF
)
if [ -n "$missing" ] && [ "${DRY_RUN:-0}" != 1 ]; then
  echo "gpu_train: missing Python packages: $missing (carry their wheels in $GPU_WHEELS)" >&2
  exit 1
fi
[ -n "$missing" ] && say "missing Python packages (dry run goes on): $missing"

if [ -e "$GPU_DATA" ]; then
  if [ "${DRY_RUN:-0}" = 1 ]; then
    say "would use the carried data $GPU_DATA"
  elif [ -d "$GPU_DATA" ]; then
    mkdir -p "$DATA_ROOT" && cp -r "$GPU_DATA"/. "$DATA_ROOT"/
  else
    mkdir -p "$DATA_ROOT" && tar -xzf "$GPU_DATA" -C "$DATA_ROOT"
  fi
elif ! "$PY" -c "import mitsuba" 2>/dev/null; then
  say "no carried data and no mitsuba: the recipe's data cannot be rendered here"
  [ "${DRY_RUN:-0}" = 1 ] || exit 1
elif [ -z "${DENOISER_MI_VARIANT:-}" ]; then
  # The LLVM variant needs a libLLVM >= 16, which the GPU machine may lack; Mitsuba's scalar variant
  # renders ~4x slower than LLVM on the same cores (measured here), so the CUDA variant comes
  # second: a 1-spp Cornell box rendered with it decides.
  DENOISER_MI_VARIANT=$("$PY" - <<'EOF'
import subprocess
import sys

from rendering.backend import LLVM_VARIANT, SCALAR_VARIANT, find_libllvm

if find_libllvm().path is not None:
    print(LLVM_VARIANT)
else:
    probe = "import mitsuba as mi; mi.set_variant('cuda_ad_rgb'); mi.render(mi.load_dict(mi.cornell_box()), spp=1)"
    works = subprocess.run([sys.executable, "-c", probe], capture_output=True).returncode == 0
    print("cuda_ad_rgb" if works else SCALAR_VARIANT)
EOF
)
  export DENOISER_MI_VARIANT
  case $DENOISER_MI_VARIANT in
    scalar_rgb) say "renders with Mitsuba's scalar_rgb: no libLLVM >= 16 and no working CUDA variant (slow)" ;;
    *) say "renders with Mitsuba's $DENOISER_MI_VARIANT" ;;
  esac
else
  say "renders with Mitsuba's $DENOISER_MI_VARIANT (DENOISER_MI_VARIANT)"
fi

TRAIN=("$PY" -m training.cli --recipe "$RECIPE" --out "$RUN_DIR" --data-root "$DATA_ROOT" --device "$DEVICE"
       --minutes "$MINUTES" --no-progress)
if [ "${DRY_RUN:-0}" = 1 ]; then
  say "dry run: ${TRAIN[*]}"
  "$PY" -m training.cli --recipe "$RECIPE" --out "$RUN_DIR" --data-root "$DATA_ROOT" --dry-run
  exit 0
fi

start=$(date +%s)
"${TRAIN[@]}"
say "done in $(( $(date +%s) - start )) s; the run (checkpoints, log.jsonl, curves.png per stage) is in $RUN_DIR"
du -sh "$RUN_DIR"/* 2>/dev/null || true
cat <<EOF
gpu_train: to bring it back: the device tool returns everything under \$OUT (files_at in its reply);
gpu_train: copy that folder to runs/$(basename "$RUN_DIR") in the repository, then on any machine
gpu_train:   train --recipe $RECIPE --out runs/$(basename "$RUN_DIR")        (continues where it stopped)
gpu_train: and score it: python -m benchmarks.evaluate --models runs/$(basename "$RUN_DIR")/<stage>/best.ckpt
EOF
