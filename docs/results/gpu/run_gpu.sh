#!/usr/bin/env bash
# The GPU check of issue 13, as run through the device tool on one H100 (a bare machine each time):
# wheels carried in .whl/ (gsplat 1.5.3 and the project's requirements the image lacks), scenes in .gpu/data/.
#   bash docs/results/gpu/run_gpu.sh parity train bench suite     # the phases to run, in order
# Every phase has its own time limit; logs go to $OUT/<phase>.log.
set -u
OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE KC_SHARED_DATA=$PWD/.gpu/data
export TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 TORCH_EXTENSIONS_DIR=/tmp/torch_ext
phase() { local name=$1 limit=$2; shift 2; echo "== $name ($(date +%T))"; timeout "$limit" "$@" 2>&1 | tee "$OUT/$name.log"; echo "== $name exit ${PIPESTATUS[0]}"; }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
python3 -m pip install -q --no-index --no-deps --no-compile .whl/*.whl && python3 -m pip install -q --no-index --no-deps --no-build-isolation -e . || exit 1
python3 -c "import torch, numba, numpy; print('torch', torch.__version__, 'numba', numba.__version__, 'numpy', numpy.__version__)"
phase compile 300 python3 -c "import time; t=time.time(); from gsplat.cuda._backend import _C; assert _C is not None; print('gsplat CUDA build', round(time.time()-t,1), 's')"
for p in "$@"; do case $p in
parity) phase parity 200 env KC_PARITY_REPORT=$OUT/parity.json python3 -m pytest -q -rs tests/render/test_gsplat_cuda.py tests/losses/test_wavelets.py::test_cuda_matches_cpu ;;
train) phase train 150 kc-train kc-splatfacto --data .gpu/data/castle-P30 --machine.device cuda --max-num-iterations 500 --steps-per-eval-all-images 250 --logging.progress-bar False --output-dir /tmp/runs spars3r --downscale-factor 4 ;;
bench) phase bench 300 python3 benchmarks/bench_gpu.py --scene .gpu/data/castle-P30 --downscale 1 --warmup-steps 3000 --steps 200 --rounds 3 ;;
profile) phase profile 200 python3 benchmarks/profile_gpu_step.py --scene .gpu/data/castle-P30 --warmup-steps 1000 --steps 30 ;;
suite) phase suite 240 python3 -m pytest -q -x -p no:cacheprovider tests ;;
esac; done
