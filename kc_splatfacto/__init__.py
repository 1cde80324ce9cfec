"""kc-splatfacto: KC-3DGS (Gaussian splatting with wavelet-domain supervision) as a Nerfstudio-style method."""

__version__ = "0.1.0"
