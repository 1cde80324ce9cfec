"""Model layer: Gaussian parameters, the Splatfacto-like model, density control."""
