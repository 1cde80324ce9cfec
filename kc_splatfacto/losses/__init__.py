"""Loss layer: differentiable DWT, frequency-domain losses (wavelet L1, KC, CBC) and photometric losses."""
