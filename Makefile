# Set-up and entry points. `make test` and `make demo` bootstrap everything they need on a fresh
# Debian machine: libLLVM >= 16 for Mitsuba's LLVM backend (when root), a .venv, the CPU build of
# torch, then the project itself. Each step is skipped when already done, so reruns take seconds.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
TORCH_VERSION := 2.13.0
STAMP := $(VENV)/.installed

.PHONY: test demo evaluate fuzz mutation bootstrap llvm chromium gpu-wheels clean

test: bootstrap
	$(PY) -m pytest -q

# 256x256 at 16 spp, ours and OIDN against the shipped 4096-spp reference (scenes/demo.py):
# open demo-output/report.html (each `make demo` replaces it).
demo: bootstrap
	$(VENV)/bin/render-and-denoise scenes/examples/demo.xml --res 256 256 --spp 16 \
	  --reference scenes/examples/demo_reference.exr --out demo-output --overwrite

evaluate: bootstrap
	$(PY) -m benchmarks.evaluate

# The long fuzz campaign (one core, niced): FUZZ_INPUTS more mutated files per reader, added to the
# lifetime record benchmarks/results/fuzz.json; failing inputs land in fuzz/crashes/ (docs/robustness.md).
FUZZ_INPUTS ?= 10000
fuzz: bootstrap
	OMP_NUM_THREADS=1 nice -n 10 $(PY) -m fuzz.campaign --inputs $(FUZZ_INPUTS)

# Mutation testing of the core modules against their tests (about an hour on one core): the scores
# and survivors go to benchmarks/results/mutation.json (docs/robustness.md).
mutation: bootstrap
	OMP_NUM_THREADS=1 nice -n 10 $(PY) -m mutation.runner

bootstrap: llvm chromium $(STAMP)

# Mitsuba 3.9.1's LLVM variants abort with LLVM 14/15; install Debian's libllvm19 when we can.
llvm:
	@if ls /usr/lib/*-linux-gnu/libLLVM-1[6-9].so* /usr/lib/*-linux-gnu/libLLVM-[2-9][0-9].so* \
	      /usr/lib/*-linux-gnu/libLLVM.so.1[6-9]* /usr/lib/*-linux-gnu/libLLVM.so.[2-9][0-9]* \
	      2>/dev/null | grep -q .; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing libllvm19 (Mitsuba's LLVM backend needs LLVM >= 16)"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libllvm19 >/dev/null) \
	    || echo "warning: could not install libllvm19; Mitsuba will use the slow scalar_rgb variant"; \
	else echo "warning: no libLLVM >= 16 and no root apt-get; Mitsuba will use the slow scalar_rgb variant"; fi

# The report's browser test (tests/test_viewer.py) opens report.html in Debian's headless chromium.
chromium:
	@if command -v chromium >/dev/null || command -v chromium-browser >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	  echo "installing chromium (the report's browser test)"; \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
	    chromium >/dev/null) || echo "warning: could not install chromium; the report's browser test cannot run"; \
	else echo "warning: no chromium and no root apt-get; the report's browser test cannot run"; fi

$(VENV)/bin/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(VENV)/bin/python
	$(PY) -m pip install -q --disable-pip-version-check torch==$(TORCH_VERSION)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[dev,oidn,cluster]'
	touch $(STAMP)

# Wheels for a lent GPU machine (Python 3.12, no Mitsuba, no network), packed to travel with the
# tree: docs/training.md, "On a GPU". Name shared/gpu/wheels in the device tool's carry.
GPU_WHEEL_DIR ?= shared/gpu/wheels
gpu-wheels: bootstrap
	rm -rf .tmp-gpu-wheels && $(PY) -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
	  --python-version 3.12 --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
	  --platform manylinux_2_17_x86_64 -d .tmp-gpu-wheels mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3
	rm -rf $(GPU_WHEEL_DIR) && $(PY) -m benchmarks.gpu_pack .tmp-gpu-wheels/*.whl --out $(GPU_WHEEL_DIR)
	rm -rf .tmp-gpu-wheels

clean:
	rm -rf $(VENV) *.egg-info
