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

__version__ = "0.1.0"
