"""The function API as a gsplat ``simple_trainer.py`` user calls it (docs/nerfstudio.md, "gsplat's trainer"): one
``FrequencyLoss`` on a batch of renders [C, 3, H, W] against ``prepare_target`` of the batch's ground truth gives, per
term, the mean of the values ``kc-train``'s model gives each image alone, and the gradient of that mean."""

from __future__ import annotations

import pytest
import torch

from kc_splatfacto.losses import FrequencyLossConfig
from kc_splatfacto.model.splatfacto import SplatfactoModelConfig

TERMS = ("wavelet_loss", "kc_loss", "cbc_loss")


@pytest.mark.parametrize("size", [(40, 56), (45, 61)])
def test_a_batch_gives_the_mean_of_the_models_per_image_values_and_gradients(size):
    height, width = size
    g = torch.Generator().manual_seed(0)
    batch = 3
    gt = torch.randint(0, 256, (batch, height, width, 3), generator=g, dtype=torch.uint8)  # simple_trainer's layout
    colors = torch.rand(batch, height, width, 3, generator=g, requires_grad=True)

    frequency_loss = FrequencyLossConfig().setup()  # the paper's settings
    pixels = gt.float() / 255.0
    target = frequency_loss.prepare_target(pixels.permute(0, 3, 1, 2))
    terms = frequency_loss(colors.permute(0, 3, 1, 2), target)
    assert set(terms) == set(TERMS)
    batch_grad = torch.autograd.grad(sum(terms.values()), colors)[0]

    model = SplatfactoModelConfig(num_downscales=0, frequency=FrequencyLossConfig()).setup().train()
    per_image, per_image_grads = [], []
    for b in range(batch):
        pred = colors[b].detach().clone().requires_grad_()
        losses = model.get_loss_dict({"rgb": pred, "background": torch.zeros(3)}, {"image": gt[b], "image_idx": b})
        per_image.append({term: float(losses[term].detach()) for term in TERMS})
        per_image_grads.append(torch.autograd.grad(sum(losses[t] for t in TERMS), pred)[0])
    for term in TERMS:
        mean = sum(values[term] for values in per_image) / batch
        assert float(terms[term].detach()) == pytest.approx(mean, rel=1e-5), term
    assert torch.allclose(batch_grad, torch.stack(per_image_grads) / batch, rtol=1e-4, atol=1e-9)
