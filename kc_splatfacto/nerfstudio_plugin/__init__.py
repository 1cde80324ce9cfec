"""kc-splatfacto as a nerfstudio plugin: ``ns-train kc-splatfacto`` (and the paper's ablations, ``splatfacto-cpu``) and
the ``spars3r`` dataparser, registered under nerfstudio's own entry-point groups.

- :mod:`.methods`: the entry points (``nerfstudio.method_configs``): nerfstudio's Splatfacto trainer settings with
  :class:`.model.KCSplatfactoModelConfig`; safe to import (a missing part lists the methods and names what to install).
- :mod:`.model`: ``KCSplatfactoModel``, nerfstudio's ``SplatfactoModel`` plus KC-3DGS's three wavelet-domain terms in
  its loss dictionary, and a CPU path (the project's rasterizer and offline LPIPS) where nerfstudio needs CUDA.
- :mod:`.cpu`: what that CPU path needs (viewmats, gsplat 1.4's rasterization contract, LPIPS).
- :mod:`.dataparser`: the project's SPARS3R parser behind nerfstudio's ``DataParser``
  (``nerfstudio.dataparser_configs``).

Nothing here is imported by the rest of the package; only nerfstudio (through the entry points) and the tests in
``tests/nerfstudio_plugin`` import it, in an environment where nerfstudio is installed (``make nerfstudio-env``).
"""
