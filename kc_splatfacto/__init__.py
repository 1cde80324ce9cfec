"""kc-splatfacto: KC-3DGS (Gaussian splatting with wavelet-domain supervision) as a Nerfstudio-style method."""

import os

# The one place the OpenMP wait policy is set, before torch (imported only below this package) loads its runtime:
# spin-waiting OpenMP threads fight the rasterizer's numba threads for the cores. Every entry point (CLIs, tests,
# benchmarks) imports this package first; a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# ...but a fully passive pool sleeps between parallel regions and every torch op or numba loop then pays its wake-up.
# A short spin before sleeping (GNU OpenMP's count, which overrides the passive policy's 0; far below the default
# 300000) keeps consecutive regions warm without that fight. Measurements: docs/performance.md ("A warm thread pool").
os.environ.setdefault("GOMP_SPINCOUNT", "10000")
# numba's OpenMP pool starts with NUMBA_NUM_THREADS threads (default: every core) and, sharing libgomp with torch,
# resets torch's thread count to that number when it starts: OMP_NUM_THREADS=1 alone still ran two threads. A user's
# OMP_NUM_THREADS therefore also caps numba (kc-bench's workers rely on it), unless NUMBA_NUM_THREADS is set.
if os.environ.get("OMP_NUM_THREADS", "").strip().isdigit() and int(os.environ["OMP_NUM_THREADS"]) > 0:
    os.environ.setdefault("NUMBA_NUM_THREADS", os.environ["OMP_NUM_THREADS"].strip())

__version__ = "0.1.0"
