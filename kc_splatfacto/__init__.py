"""kc-splatfacto: KC-3DGS (Gaussian splatting with wavelet-domain supervision) as a Nerfstudio-style method."""

import os

# The one place the OpenMP wait policy is set, before torch (imported only below this package) loads its runtime:
# the default spin-waiting threads fight the rasterizer's numba threads and make small torch ops ~100x slower on
# small machines. Every entry point (CLIs, tests, benchmarks) imports this package first; a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
