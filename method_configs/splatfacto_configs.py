"""Method specifications: ``splatfacto``, ``kc-splatfacto`` (the paper's defaults), its ``fine``-weighting variant and
the ablations of the paper's supplementary table "Ablation study on loss components" (sparse-view, Splatfacto).

Mapping of the paper's ablation rows to config values (``pipeline.model.ssim_lambda`` and ``pipeline.model.frequency``,
a :class:`~kc_splatfacto.losses.frequency.FrequencyLossConfig` whose defaults are the paper's):

| paper row                          | method name                 | ssim_lambda | wavelet | weighting | kc   | cbc  | cbc_correlation |
|------------------------------------|-----------------------------|-------------|---------|-----------|------|------|-----------------|
| L1+SSIM                            | splatfacto                  | 0.2         | 0       |           | 0    | 0    |                 |
| L1+Wavelet                         | kc-ablation-l1-wavelet      | 0.0         | 1e-3    | paper     | 0    | 0    |                 |
| L1+SSIM+Wavelets                   | kc-ablation-wavelet         | 0.2         | 1e-3    | paper     | 0    | 0    |                 |
| L1+SSIM+(Unscaled)Wavelets         | kc-ablation-unscaled-wavelet| 0.2         | 1e-3    | uniform   | 0    | 0    |                 |
| L1+SSIM+KC+CBC+Wavelets            | kc-splatfacto               | 0.2         | 1e-3    | paper     | 1e-5 | 1e-2 | False           |
| L1+SSIM+KC+CBC+(Heavy)Wavelets     | kc-ablation-heavy-wavelet   | 0.2         | 1e-1    | paper     | 1e-5 | 1e-2 | False           |
| L1+SSIM+KC+(Scaled)CBC+Wavelets    | kc-ablation-scaled-cbc      | 0.2         | 1e-3    | paper     | 1e-5 | 1e-2 | True            |

The paper gives no numbers for "Heavy" and "Scaled"; our reading: "(Heavy)Wavelets" is the wavelet weight raised
100-fold (1e-1, between the 1e-2 and 1.0 of its sensitivity table), "(Scaled)CBC" is the CBC computed on correlations
(covariances divided by the band standard deviations, so it is invariant to each band's scale). "(Unscaled)Wavelets"
drops the 2^j level weights (uniform). "L1+Wavelet" drops the D-SSIM term (ssim_lambda 0, main loss = L1).
``kc-splatfacto-fine`` weights finer levels heavier (2^(J-j+1)), as the paper's text (not its equation) describes.
``kc-splatfacto-corr`` is the paper's weights with the CBC on correlations.
``splatfacto-mcmc`` and ``kc-splatfacto-mcmc`` are ``splatfacto`` and ``kc-splatfacto`` with MCMC densification
(``strategy="mcmc"``, nerfstudio main's settings: at most ``max_gs_num`` Gaussians), dead below gsplat's and the
paper's opacity 0.005 (``MCMC_CULL_ALPHA``) rather than Splatfacto's 0.1; in ns-train too (the plugin's model
swaps the strategy, which nerfstudio 1.1.5's Splatfacto lacks).
"""

from __future__ import annotations

import dataclasses

from kc_splatfacto.engine.trainer import TrainerConfig
from kc_splatfacto.losses.frequency import FrequencyLossConfig
from kc_splatfacto.model.splatfacto import SplatfactoModelConfig
from kc_splatfacto.registry import MethodSpecification

PAPER = FrequencyLossConfig()
"""the paper's frequency-loss settings (Method section; supplementary 'Hyperparameter' table)"""
WAVELET_ONLY = dataclasses.replace(FrequencyLossConfig.off(), wavelet_weight=PAPER.wavelet_weight)
"""the paper's wavelet L1 alone (KC and CBC off): the wavelet ablations"""
MCMC_CULL_ALPHA = 0.005
"""the MCMC methods' ``cull_alpha_thresh``, which nerfstudio's main branch passes as MCMC's dead-opacity threshold:
gsplat's ``MCMCStrategy`` default and the paper's. Splatfacto's 0.1 kills every Gaussian the opacity regularisation
has pushed a few Adam steps down, and relocation then piles them onto the views just trained: on the 64x48 demo scene
(100 steps, steps_scale 0.02) the test PSNR fell to 13.6 dB with 0.1 and reached 20.5 dB with 0.005 (the default
strategy: 20.8 dB)"""
CORRELATION_CBC = dataclasses.replace(PAPER, cbc_correlation=True)
"""the paper's settings with the CBC on band correlations: the "(Scaled)CBC" ablation row and kc-splatfacto-corr"""
LOWPASS = dataclasses.replace(FrequencyLossConfig.off(), lowpass_weight=1.0, wave="haar", wavelet_levels=2)
"""low-pass wavelet supervision as LGDWT-GS publishes its defaults: a two-level Haar DWT, L1 on LL1 and LL2 weighted
1 and 0.5, every high-frequency band 0 (the weight is the published one, not tuned on our scenes)"""


def _trainer(method_name: str, frequency: FrequencyLossConfig | None = None, **model_overrides) -> TrainerConfig:
    """Splatfacto's TrainerConfig named ``method_name`` with these model fields (``frequency``: the wavelet losses;
    None: off), with the scene plan on (``--pipeline.model.plan off``: the paper's and Splatfacto's fixed settings,
    which are SplatfactoModelConfig's own default, so a config.yml written before the plan existed reads as one)."""
    config = TrainerConfig(method_name=method_name)
    frequency = dataclasses.replace(frequency) if frequency is not None else FrequencyLossConfig.off()  # own copy
    model_overrides.setdefault("plan", "on")
    config.pipeline.model = dataclasses.replace(SplatfactoModelConfig(), frequency=frequency, **model_overrides)
    return config


splatfacto = MethodSpecification(
    config=_trainer("splatfacto"),
    description="Splatfacto baseline (nerfstudio 1.1.5 defaults): 0.8 L1 + 0.2 (1 - SSIM)",
)
kc_splatfacto = MethodSpecification(
    config=_trainer("kc-splatfacto", PAPER),
    description="KC-3DGS: Splatfacto + wavelet L1 (1e-3, 2^j) + supervised KC (1e-5) + CBC (1e-2), db3, 3 levels",
)
kc_splatfacto_fine = MethodSpecification(
    config=_trainer("kc-splatfacto-fine", dataclasses.replace(PAPER, wavelet_weighting="fine")),
    description="KC-3DGS with the 'fine' wavelet weighting 2^(J-j+1) (finer levels heavier, as the paper's text says)",
)
ablation_l1_wavelet = MethodSpecification(
    config=_trainer("kc-ablation-l1-wavelet", WAVELET_ONLY, ssim_lambda=0.0),
    description="ablation L1+Wavelet: L1 + wavelet L1 (1e-3), no SSIM, no KC/CBC",
)
ablation_wavelet = MethodSpecification(
    config=_trainer("kc-ablation-wavelet", WAVELET_ONLY),
    description="ablation L1+SSIM+Wavelets: Splatfacto + wavelet L1 (1e-3), no KC/CBC",
)
ablation_unscaled_wavelet = MethodSpecification(
    config=_trainer("kc-ablation-unscaled-wavelet",
                    dataclasses.replace(WAVELET_ONLY, wavelet_weighting="uniform")),
    description="ablation L1+SSIM+(Unscaled)Wavelets: wavelet L1 without the 2^j level weights",
)
ablation_heavy_wavelet = MethodSpecification(
    config=_trainer("kc-ablation-heavy-wavelet", dataclasses.replace(PAPER, wavelet_weight=1e-1)),
    description="ablation L1+SSIM+KC+CBC+(Heavy)Wavelets: KC-3DGS with wavelet weight 1e-1",
)
ablation_scaled_cbc = MethodSpecification(
    config=_trainer("kc-ablation-scaled-cbc", CORRELATION_CBC),
    description="ablation L1+SSIM+KC+(Scaled)CBC+Wavelets: KC-3DGS with CBC on correlations",
)
splatfacto_lowpass = MethodSpecification(
    config=_trainer("splatfacto-lowpass", LOWPASS),
    description="Splatfacto + L1 on the wavelet approximation bands (two-level Haar, LL1 1.0, LL2 0.5: LGDWT-GS's "
                "published defaults), the low-pass counterpart of KC-3DGS's detail-band terms",
)
kc_splatfacto_corr = MethodSpecification(
    config=_trainer("kc-splatfacto-corr", CORRELATION_CBC),
    description="KC-3DGS tuned on castle-P30: the paper's weights with the CBC on band correlations "
                "(docs/results/castle-P30-sweep)",
)
"""``kc-splatfacto`` with one change, the cross-band term on band correlations (covariances divided by the bands'
standard deviations, invariant to each band's scale), so that the CBC pulls with a weight comparable to the other
terms; on covariances at the paper's weight its gradient is orders of magnitude below them (docs/losses.md,
"Gradient shares"). ``kc-splatfacto`` (the paper's) stays the reference."""
splatfacto_mcmc = MethodSpecification(
    config=_trainer("splatfacto-mcmc", strategy="mcmc", cull_alpha_thresh=MCMC_CULL_ALPHA),
    description="Splatfacto with MCMC densification (relocation, 5% growth per refinement up to max_gs_num, noise)",
)
kc_splatfacto_mcmc = MethodSpecification(
    config=_trainer("kc-splatfacto-mcmc", PAPER, strategy="mcmc", cull_alpha_thresh=MCMC_CULL_ALPHA),
    description="KC-3DGS with MCMC densification (relocation, 5% growth per refinement up to max_gs_num, noise)",
)
