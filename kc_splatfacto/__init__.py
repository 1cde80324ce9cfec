"""kc-splatfacto: KC-3DGS (Gaussian splatting with wavelet-domain supervision) as a Nerfstudio-style method."""

import os

# The one place the OpenMP wait policy is set, before torch (imported only below this package) loads its runtime:
# the default spin-waiting threads fight the rasterizer's numba threads and make small torch ops ~100x slower on
# small machines. Every entry point (CLIs, tests, benchmarks) imports this package first; a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# ...but a fully passive pool sleeps between parallel regions, and waking it costs ~50 us per region: every torch op
# over its grain size (32k elements) and every numba parallel loop paid that (a 58k-element add took 51 us on 2
# threads, 6 us on 1). A short spin before sleeping (GNU OpenMP's count, which overrides the passive policy's 0;
# ~tens of microseconds, far below the default 300000) keeps consecutive regions warm without the spinning fights
# above: bench_train's step ~5 % faster (docs/performance.md, sixth session).
os.environ.setdefault("GOMP_SPINCOUNT", "10000")

__version__ = "0.1.0"
