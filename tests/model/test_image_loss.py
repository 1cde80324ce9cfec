"""The image-space loss region and its CUDA-graph replay (model/image_loss.py).

On the CPU the capture is replaced by a stand-in that returns the region itself, so what a graph would replay (the
tensors-only region with the ground truth's cached target passed in) is held to the eager loss here; the check at
first use and the fallbacks are exercised with stand-ins that fail. On a GPU the real capture is compared with the
eager loss over several images and two sizes."""

from __future__ import annotations

import pytest
import torch

from kc_splatfacto import backend
from kc_splatfacto.losses import FrequencyLoss, FrequencyLossConfig
from kc_splatfacto.model.image_loss import ImageLoss
from tests.losses.test_frequency_terms import WithEnergy, add_energy_term


class _OnAnyDevice(ImageLoss):
    """The graph path on the CPU (the region replayed by whatever ``capture`` gives)."""

    def _graphs_apply(self, render, gt):
        return render.requires_grad


def _pair(size, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*size, 3, generator=g), torch.rand(*size, 3, generator=g)


def _terms_and_grad(loss, render, gt, key):
    leaf = render.clone().requires_grad_(True)
    terms = loss(leaf, gt, key)
    grad = torch.autograd.grad(torch.stack(list(terms.values())).sum(), leaf)[0]
    return {name: value.detach() for name, value in terms.items()}, grad


@pytest.mark.parametrize("frequency", [FrequencyLossConfig(), FrequencyLossConfig(kc_weight=0.0), None])
def test_the_replayed_region_equals_the_eager_loss_for_every_image_and_size(frequency):
    captured = []

    def capture(region, sample):
        captured.append(tuple(t.shape for t in sample))
        return region

    frequency_loss = None if frequency is None else frequency.setup()
    graphed = _OnAnyDevice(0.2, frequency_loss, capture=capture)
    eager = ImageLoss(0.2, None if frequency is None else frequency.setup(), cuda_graphs=False)
    with backend.torch_reference():  # the torch path: the one a GPU runs, with the fused frequency terms
        for size in ((48, 64), (40, 56)):
            for image in range(3):
                render, gt = _pair(size, seed=10 * image + size[0])
                terms, grad = _terms_and_grad(graphed, render, gt, key=(image, size))
                expected, expected_grad = _terms_and_grad(eager, render, gt, key=(image, size))
                assert list(terms) == list(expected)
                for name in expected:
                    torch.testing.assert_close(terms[name], expected[name], rtol=1e-6, atol=0)
                torch.testing.assert_close(grad, expected_grad, rtol=1e-6, atol=1e-9)
    assert len(captured) == 2  # one capture per size, shared by its images
    assert graphed.cuda_graphs


def test_a_term_without_a_fused_kernel_runs_eagerly_beside_the_graph_that_holds_the_rest(monkeypatch):
    add_energy_term(monkeypatch, fused_kernel=False)
    captured = []

    def capture(region, sample):
        captured.append(region)
        return lambda *inputs: captured.append("replay") or region(*inputs)

    graphed = _OnAnyDevice(0.2, FrequencyLoss(WithEnergy()), capture=capture)
    eager = ImageLoss(0.2, FrequencyLoss(WithEnergy()), cuda_graphs=False)
    with backend.torch_reference():
        for image in range(2):
            render, gt = _pair((48, 64), seed=image)
            terms, grad = _terms_and_grad(graphed, render, gt, key=image)
            expected, expected_grad = _terms_and_grad(eager, render, gt, key=image)
            assert list(terms) == list(expected) == ["main_loss", "wavelet_loss", "kc_loss", "cbc_loss", "energy_loss"]
            for name in expected:
                torch.testing.assert_close(terms[name], expected[name], rtol=1e-6, atol=0)
            torch.testing.assert_close(grad, expected_grad, rtol=1e-6, atol=1e-9)
        region = captured[0]
        render, gt = _pair((48, 64), seed=0)
        slots = graphed.frequency_loss.stage(render.permute(2, 0, 1)[None], gt.permute(2, 0, 1)[None], key=0).tensors
        # the graph holds the main loss and the three fused terms; the new one is not in it
        assert len(region(render, gt, *slots)) == 4
    assert graphed.cuda_graphs and captured.count("replay") >= 2


def test_a_failed_capture_or_a_replay_that_disagrees_turns_the_graphs_off_with_one_warning():
    render, gt = _pair((48, 64), seed=1)
    eager = ImageLoss(0.2, FrequencyLossConfig().setup(), cuda_graphs=False)

    def failing(region, sample):
        raise RuntimeError("operation not permitted when stream is capturing")

    def wrong(region, sample):
        return lambda *inputs: tuple(2.0 * value for value in region(*inputs))

    with backend.torch_reference():
        expected, expected_grad = _terms_and_grad(eager, render, gt, key=0)
        for capture, message in ((failing, "capturing the image loss at \\(48, 64\\) failed"),
                                 (wrong, "disagrees with the eager one")):
            loss = _OnAnyDevice(0.2, FrequencyLossConfig().setup(), capture=capture)
            with pytest.warns(UserWarning, match=message):
                terms, grad = _terms_and_grad(loss, render, gt, key=0)
            assert not loss.cuda_graphs
            for name in expected:
                torch.testing.assert_close(terms[name], expected[name], rtol=1e-6, atol=0)
            torch.testing.assert_close(grad, expected_grad)


def test_on_the_cpu_the_loss_is_eager_and_never_captured():
    def capture(region, sample):
        raise AssertionError("no capture on the CPU")

    render, gt = _pair((48, 64), seed=2)
    loss = ImageLoss(0.2, FrequencyLossConfig().setup(), capture=capture)
    terms, _ = _terms_and_grad(loss, render, gt, key=0)
    assert set(terms) == {"main_loss", "wavelet_loss", "kc_loss", "cbc_loss"}


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (the GPU campaign runs it)")
def test_cuda_graph_replay_equals_the_eager_loss_on_a_gpu():
    graphed = ImageLoss(0.2, FrequencyLossConfig().setup())
    eager = ImageLoss(0.2, FrequencyLossConfig().setup(), cuda_graphs=False)
    for size in ((96, 128), (192, 256)):
        for image in range(3):
            render, gt = (t.cuda() for t in _pair(size, seed=image))
            terms, grad = _terms_and_grad(graphed, render, gt, key=(image, size))
            expected, expected_grad = _terms_and_grad(eager, render, gt, key=(image, size))
            for name in expected:
                torch.testing.assert_close(terms[name], expected[name], rtol=1e-5, atol=1e-8)
            scale = expected_grad.abs().max()
            torch.testing.assert_close(grad / scale, expected_grad / scale, rtol=0, atol=1e-5)
    assert graphed.cuda_graphs and len(graphed._graphs) == 2
