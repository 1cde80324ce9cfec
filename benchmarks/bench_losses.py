"""Forward+backward time of dwt2 and FrequencyLoss vs ptwt / pytorch_wavelets (when importable), with ratios.

Run: `.venv/bin/python benchmarks/bench_losses.py [--sizes 256 512 1024] [--device cpu|cuda] [--quick]`.
Every timing is a median over repeats in this same run. ptwt and pytorch_wavelets are NOT dependencies: the rows say
"not installed" when they are missing. The "separable" row is the alternative DWT layout (a row pass then a column
pass, two strided convs per level) measured against the shipped one (one strided conv with four 2D filters).
With the shared castle-P30 scene present (../shared/data or KC_SHARED_DATA), it also prints the padding table of
docs/losses.md: the finest-band kurtosis of a blurred natural photo under each boundary mode.
Targets: dwt2 at least as fast as ptwt at 512 and 1024 px; FrequencyLoss with cached GT within 1.5x of one
dwt2 forward+backward.
"""

import os

import kc_splatfacto  # noqa: E402,F401  (sets OMP_WAIT_POLICY before torch loads)

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402
from kornia.filters import gaussian_blur2d  # noqa: E402

from kc_splatfacto.losses import FrequencyLoss, dwt2  # noqa: E402
from kc_splatfacto.losses.wavelets import WaveletCoeffs, _pad, daubechies_filters, filter_length  # noqa: E402

WAVE, LEVELS, MODE = "db3", 3, "symmetric"


def dwt2_separable(x: torch.Tensor, wave: str = WAVE, levels: int = LEVELS, mode: str = MODE) -> WaveletCoeffs:
    """The alternative layout: per level, a strided row conv (lo, hi along W) then a strided column conv."""
    dec_lo, dec_hi = daubechies_filters(wave)
    flen = filter_length(wave)
    taps = torch.as_tensor(np.stack([dec_lo[::-1], dec_hi[::-1]]), dtype=x.dtype, device=x.device)  # [2, L]
    along_w = taps.view(2, 1, 1, flen)
    along_h = taps.view(2, 1, flen, 1).repeat(2, 1, 1, 1)  # groups=2: (lo_W -> lo_H, hi_H), (hi_W -> lo_H, hi_H)
    batch, channels, height, width = x.shape
    current = x.reshape(batch * channels, 1, height, width)
    details = []
    for _ in range(levels):
        padded = _pad(current, flen, mode)
        rows = F.conv2d(padded, along_w, stride=(1, 2))  # [N, 2, Hp, w]
        out = F.conv2d(rows, along_h, stride=(2, 1), groups=2)  # [N, 4, h, w] = (LL, HL=cH, LH=cV, HH=cD)
        h, w = out.shape[-2:]
        details.append(out[:, 1:].reshape(batch, channels, 3, h, w))
        current = out[:, :1]
    return WaveletCoeffs(current.reshape(batch, channels, *current.shape[-2:]), details)


def _coeff_sum(coeffs) -> torch.Tensor:
    return coeffs.approx.sum() + sum(d.sum() for d in coeffs.details)


def make_cases(device: torch.device):
    """name -> (setup(size) -> closure running one forward+backward) or a reason string."""
    cases = {}

    def ours(size):
        x = torch.rand(1, 3, size, size, device=device, requires_grad=True)
        return lambda: _coeff_sum(dwt2(x, WAVE, LEVELS, MODE)).backward()

    def separable(size):
        x = torch.rand(1, 3, size, size, device=device, requires_grad=True)
        return lambda: _coeff_sum(dwt2_separable(x)).backward()

    cases["dwt2 (ours, 4-filter conv)"] = ours
    cases["dwt2 separable (alternative)"] = separable

    try:
        import ptwt

        def run_ptwt(size):
            x = torch.rand(1, 3, size, size, device=device, requires_grad=True)

            def step():
                coeffs = ptwt.wavedec2(x, WAVE, level=LEVELS, mode=MODE)
                total = coeffs[0].sum() + sum(t.sum() for level in coeffs[1:] for t in level)
                total.backward()

            return step

        cases["ptwt.wavedec2"] = run_ptwt
    except ImportError:
        cases["ptwt.wavedec2"] = "not installed"

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # its pkg_resources import warns
            from pytorch_wavelets import DWTForward

        def run_pw(size):
            x = torch.rand(1, 3, size, size, device=device, requires_grad=True)
            transform = DWTForward(J=LEVELS, wave=WAVE, mode=MODE).to(device)

            def step():
                low, highs = transform(x)
                (low.sum() + sum(h.sum() for h in highs)).backward()

            return step

        cases["pytorch_wavelets.DWTForward"] = run_pw
    except ImportError:
        cases["pytorch_wavelets.DWTForward"] = "not installed"

    def loss_case(cached):
        def setup(size):
            pred = torch.rand(1, 3, size, size, device=device, requires_grad=True)
            gt = torch.rand(1, 3, size, size, device=device)
            loss = FrequencyLoss()
            if cached:
                target = loss.prepare_target(gt)
                return lambda: sum(loss(pred, target).values()).backward()
            return lambda: sum(loss(pred, loss.prepare_target(gt)).values()).backward()  # the GT's DWT every step

        return setup

    cases["FrequencyLoss, cached GT"] = loss_case(True)
    cases["FrequencyLoss, GT image"] = loss_case(False)
    return cases


def time_interleaved(steps: dict, device: torch.device, repeats: int) -> dict:
    """Median ms per step; the steps run round-robin so the machine's load drifts hit every case alike."""

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for step in steps.values():
        for _ in range(2):
            step()
    sync()
    samples = {name: [] for name in steps}
    for _ in range(repeats):
        for name, step in steps.items():
            start = time.perf_counter()
            step()
            sync()
            samples[name].append((time.perf_counter() - start) * 1e3)
    return {name: statistics.median(values) for name, values in samples.items()}


def padding_table(sigmas=(0.0, 1.5, 3.0)) -> None:
    """Finest-level kurtosis (H, V, D; channel mean) of castle-P30 0000.jpg (768x512), blurred, per boundary mode."""
    from pathlib import Path

    from kc_splatfacto.losses import MODES, band_kurtosis

    shared = Path(os.environ.get("KC_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
    photo = shared / "castle-P30" / "images" / "0000.jpg"
    if not photo.exists():
        print(f"padding table: {photo} not found (set KC_SHARED_DATA), skipped")
        return
    from PIL import Image

    with Image.open(photo) as img:
        rgb = torch.from_numpy(np.asarray(img.convert("RGB"), dtype=np.float64) / 255.0)
    image = rgb.permute(2, 0, 1)[None].contiguous()
    print(
        f"\npadding table: {photo.name} {image.shape[-1]}x{image.shape[-2]}, Gaussian blur sigma (px), db3, "
        f"finest-level excess kurtosis (cH, cV, cD), mean over RGB; last column: mean of all 9 bands"
    )
    print(f"{'sigma':>6s} {'mode':14s} {'cH':>9s} {'cV':>9s} {'cD':>9s} {'all 9':>9s}")
    for sigma in sigmas:
        blurred = _gaussian_blur(image, sigma) if sigma > 0 else image
        for mode in MODES:
            kurtosis = band_kurtosis(dwt2(blurred, "db3", 3, mode)).mean(dim=(0, 1))
            h, v, d = kurtosis[:3].tolist()
            print(f"{sigma:6.1f} {mode:14s} {h:9.2f} {v:9.2f} {d:9.2f} {kurtosis.mean().item():9.2f}")


def _gaussian_blur(image: torch.Tensor, sigma: float) -> torch.Tensor:
    size = 2 * int(3 * sigma + 0.5) + 1
    # reflect borders: the blur itself must not create the border steps the table is about
    return gaussian_blur2d(image, (size, size), (sigma, sigma), border_type="reflect")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[256, 512, 1024])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--quick", action="store_true", help="fewer repeats")
    parser.add_argument("--no-padding-table", action="store_true", help="skip the castle-P30 padding table")
    args = parser.parse_args()
    device = torch.device(args.device)
    cases = make_cases(device)
    base = "dwt2 (ours, 4-filter conv)"
    print(
        f"device {device}, torch {torch.__version__}, threads {torch.get_num_threads()}, {WAVE} {LEVELS} levels "
        f"{MODE}, batch 1 x 3 channels, forward+backward, median ms"
    )
    results = {}
    for size in args.sizes:
        repeats = (5 if args.quick else 21) if size <= 512 else (3 if args.quick else 9)
        steps = {name: setup(size) for name, setup in cases.items() if not isinstance(setup, str)}
        timings = time_interleaved(steps, device, repeats)
        for name, setup in cases.items():
            results[(name, size)] = setup if isinstance(setup, str) else timings[name]
    header = f"{'case':32s}" + "".join(f"{f'{s} px ms':>12s}{'ratio':>8s}" for s in args.sizes)
    print(header)
    print("-" * len(header))
    for name in cases:
        row = f"{name:32s}"
        for size in args.sizes:
            value = results[(name, size)]
            if isinstance(value, str):
                row += f"{value:>20s}"
            else:
                row += f"{value:12.2f}{value / results[(base, size)]:8.2f}"
        print(row)
    print(f"ratio = time / '{base}' at the same size (ratio > 1: slower than our dwt2)")
    for size in args.sizes:
        ptwt_ms = results[("ptwt.wavedec2", size)]
        cached = results[("FrequencyLoss, cached GT", size)] / results[(base, size)]
        verdict = "n/a" if isinstance(ptwt_ms, str) else ("yes" if results[(base, size)] <= ptwt_ms else "NO")
        print(
            f"{size} px: dwt2 at least as fast as ptwt: {verdict}; FrequencyLoss cached / dwt2 = {cached:.2f} "
            f"(target <= 1.5: {'yes' if cached <= 1.5 else 'NO'})"
        )
    if not args.no_padding_table:
        padding_table()


if __name__ == "__main__":
    main()
