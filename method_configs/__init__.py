"""Method specifications registered through the ``kc_splatfacto.method_configs`` entry-point group."""
