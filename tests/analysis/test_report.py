"""Report aggregation: numbers against numpy, PNGs that decode, the markdown table's deltas, and (with the trainer)
a real 2-method bench run with one curve per method and monotone times."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from kc_splatfacto.analysis import report
from kc_splatfacto.engine.metrics_log import read_metrics


def _fake_runs(tmp_path):
    """metrics.jsonl files of 2 methods x 3 seeds, written as the trainer does (train and eval records mixed)."""
    rng = np.random.default_rng(0)
    rows, truth = [], {}
    for method, offset, speed in (("splatfacto", 20.0, 1.0), ("kc-splatfacto", 20.5, 1.3)):
        for seed in range(3):
            records, t = [], 0.0
            for step in (1, 10, 100, 300):
                t += speed * step * 0.01 + rng.uniform(0, 0.1)
                records.append({"kind": "train", "step": step, "elapsed_s": t, "train_s": t, "main_loss": 0.1})
                psnr = offset + np.log10(step) + rng.normal(0, 0.2)
                ssim = 0.5 + 0.05 * np.log10(step) + rng.normal(0, 0.01)
                records.append({"kind": "eval", "step": step, "elapsed_s": t + 1.0, "train_s": t, "psnr": psnr,
                                "ssim": ssim, "lpips": None, "lpips_unavailable": "no weights", "num_images": 4})
                truth[(method, seed, step)] = (psnr, ssim, t)
            # rows count time from step 1 at the rate of steps 1 -> 10 (the first step's start-up left out)
            t1, t10 = truth[(method, seed, 1)][2], truth[(method, seed, 10)][2]
            start_up = max(0.0, t1 - (t10 - t1) / 9)
            for step in (1, 10, 100, 300):
                psnr, ssim, t = truth[(method, seed, step)]
                truth[(method, seed, step)] = (psnr, ssim, t - start_up)
            path = tmp_path / method / str(seed) / "metrics.jsonl"
            path.parent.mkdir(parents=True)
            path.write_text("\n".join(json.dumps(r) for r in records) + "\n")
            rows += report.eval_rows(read_metrics(path), "scene", method, seed, path.parent)
    return rows, truth


def test_aggregation_matches_numpy(tmp_path):
    rows, truth = _fake_runs(tmp_path)
    assert len(rows) == 2 * 3 * 4 and all(r["lpips"] is None for r in rows)
    curves = {c.method: c for c in report.aggregate_curves(rows, "psnr")}
    assert set(curves) == {"splatfacto", "kc-splatfacto"}
    for method, curve in curves.items():
        assert curve.steps.tolist() == [1, 10, 100, 300] and curve.num_seeds == 3
        values = np.array([[truth[(method, s, step)][0] for step in curve.steps] for s in range(3)])
        times = np.array([[truth[(method, s, step)][2] for step in curve.steps] for s in range(3)])
        np.testing.assert_allclose(curve.mean, values.mean(0), rtol=1e-12)
        np.testing.assert_allclose(curve.std, values.std(0), rtol=1e-12)
        np.testing.assert_allclose(curve.low, values.min(0), rtol=1e-12)
        np.testing.assert_allclose(curve.time, times.mean(0), rtol=1e-12)
    assert report.aggregate_curves(rows, "lpips") == []


def test_steps_missing_in_a_seed_are_left_out(tmp_path):
    rows, _ = _fake_runs(tmp_path)
    rows = [r for r in rows if not (r["method"] == "splatfacto" and r["seed"] == 1 and r["step"] == 10)]
    curve = next(c for c in report.aggregate_curves(rows, "ssim") if c.method == "splatfacto")
    assert curve.steps.tolist() == [1, 100, 300]


def test_summary_and_markdown_deltas(tmp_path):
    rows, truth = _fake_runs(tmp_path)
    summary = {e["method"]: e for e in report.summarize_final(rows, baseline="splatfacto")}
    base_psnr = np.mean([truth[("splatfacto", s, 300)][0] for s in range(3)])
    kc_psnr = np.mean([truth[("kc-splatfacto", s, 300)][0] for s in range(3)])
    base_ssim = np.mean([truth[("splatfacto", s, 300)][1] for s in range(3)])
    kc_ssim = np.mean([truth[("kc-splatfacto", s, 300)][1] for s in range(3)])
    assert summary["kc-splatfacto"]["psnr_delta_db"] == pytest.approx(kc_psnr - base_psnr, rel=1e-12)
    assert summary["kc-splatfacto"]["ssim_delta_pct"] == pytest.approx(100 * (kc_ssim - base_ssim) / base_ssim, rel=1e-9)
    base_t = np.mean([truth[("splatfacto", s, 300)][2] for s in range(3)])
    kc_t = np.mean([truth[("kc-splatfacto", s, 300)][2] for s in range(3)])
    assert summary["kc-splatfacto"]["time_ratio"] == pytest.approx(kc_t / base_t, rel=1e-9)
    assert summary["kc-splatfacto"]["lpips"] is None and summary["kc-splatfacto"]["lpips_delta_pct"] is None
    table = report.markdown_table(list(summary.values()), "splatfacto", lpips_note="unavailable offline")
    data_lines = [line for line in table.splitlines() if line.startswith("| scene |") and "splatfacto" in line]
    assert len(data_lines) == 2  # one line per method, baseline first
    assert "| splatfacto (baseline) |" in data_lines[0]
    kc_line = next(line for line in table.splitlines() if "| kc-splatfacto |" in line)
    assert f"{kc_psnr - base_psnr:+.2f} dB" in kc_line and "n/a" in kc_line
    assert "splatfacto (baseline)" in table and "unavailable offline" in table


def test_write_report_files_decode(tmp_path):
    rows, _ = _fake_runs(tmp_path)
    paths = report.write_report(rows, tmp_path / "out", baseline="splatfacto", lpips_note="n/a")
    assert "plot_lpips" not in paths  # no values: no empty plot
    for key in ("plot_psnr", "plot_ssim"):
        image = cv2.imread(str(paths[key]), cv2.IMREAD_COLOR)
        assert image is not None and image.shape[0] > 100 and image.shape[1] > 100 and image.std() > 0
    back = report.read_rows_csv(paths["csv"])
    assert len(back) == len(rows)
    for a, b in zip(back, rows):
        assert a["method"] == b["method"] and a["step"] == b["step"]
        assert a["psnr"] == pytest.approx(b["psnr"], rel=1e-12) and a["lpips"] is None
    assert json.loads(paths["json"].read_text())[0]["scene"] == "scene"


def test_bad_logs(tmp_path):
    with pytest.raises(FileNotFoundError, match="metrics.jsonl"):
        read_metrics(tmp_path / "metrics.jsonl")
    (tmp_path / "metrics.jsonl").write_text('{"kind": "eval", "step": 1}\n{"kind": "ev')
    with pytest.raises(ValueError, match="metrics.jsonl:2"):
        read_metrics(tmp_path / "metrics.jsonl")
    with pytest.raises(KeyError, match="elapsed_s"):
        report.eval_rows([{"kind": "eval", "step": 1}], "s", "m", 0)
    with pytest.raises(ValueError, match="no evaluation rows"):
        report.write_report([], tmp_path / "out")


def test_bench_two_methods_one_seed_demo(tmp_path):
    """kc-bench end to end on the demo scene: one curve per method, monotone times, decodable plots."""
    from kc_splatfacto.cli import bench

    out = tmp_path / "bench"
    argv = ["--data", "demo", "--methods", "splatfacto", "kc-splatfacto", "--seeds", "0",
            "--max-num-iterations", "12", "--num-evals", "3", "--output-dir", str(out)]
    assert bench.entrypoint(argv) == 0
    rows = report.read_rows_csv(out / "evals.csv")
    assert {r["method"] for r in rows} == {"splatfacto", "kc-splatfacto"}
    for metric in ("psnr", "ssim"):
        curves = report.aggregate_curves(rows, metric)
        assert sorted(c.method for c in curves) == ["kc-splatfacto", "splatfacto"]
        for curve in curves:
            assert curve.num_seeds == 1 and curve.steps.tolist() == list(bench.log_spaced_steps(12, 3))
            assert np.all(np.diff(curve.time) > 0), f"{curve.method}: training time not increasing {curve.time}"
            assert np.isfinite(curve.mean).all()
        image = cv2.imread(str(out / f"{metric}_vs_time.png"), cv2.IMREAD_COLOR)
        assert image is not None and image.std() > 0
    for method in ("splatfacto", "kc-splatfacto"):
        mine = sorted((r for r in rows if r["method"] == method), key=lambda r: r["step"])
        assert np.all(np.diff([r["elapsed_s"] for r in mine]) > 0)
        assert all(r["elapsed_s"] >= r["train_s"] for r in mine)  # wall clock includes the evaluations
    table = (out / "results.md").read_text()
    assert "splatfacto (baseline)" in table and "| kc-splatfacto |" in table
    assert (out / "command.txt").read_text().startswith("kc-bench --data demo")
    from kc_splatfacto.lpips import lpips_available

    if lpips_available("alex") is None:  # LPIPS weights installed (make install): a real LPIPS column and plot
        assert all(r["lpips"] is not None and 0 < r["lpips"] < 1 and r["lpips_net"] == "alex" for r in rows)
        assert "LPIPS (alex) ↓" in table
        image = cv2.imread(str(out / "lpips_vs_time.png"), cv2.IMREAD_COLOR)
        assert image is not None and image.std() > 0
    else:
        assert not (out / "lpips_vs_time.png").exists()
    gap = cv2.imread(str(out / "kurtosis_gap_demo.png"), cv2.IMREAD_COLOR)  # kurtosis is logged at step 10
    assert gap is not None and gap.std() > 0


def test_log_spaced_steps():
    from kc_splatfacto.cli import bench

    steps = bench.log_spaced_steps(1000, 7)
    assert steps[0] == 1 and steps[-1] == 1000 and list(steps) == sorted(set(steps))
    ratios = np.diff(np.log(steps))
    assert ratios.max() / ratios.min() < 1.2  # geometric spacing
    assert bench.log_spaced_steps(3, 10) == (1, 2, 3)
    assert bench.evaluation_steps(30000, 3, [7000]) == (1, 173, 7000, 30000)  # geomspace(1, 30000, 3): 173.2
    with pytest.raises(ValueError, match="eval-at-steps"):
        bench.evaluation_steps(1000, 3, [7000])
    with pytest.raises(ValueError):
        bench.log_spaced_steps(0, 3)


def test_mean_interval_against_printed_t_values():
    # t_{0.975, 1} = 12.706205, t_{0.975, 4} = 2.776445 (printed t tables)
    assert report.mean_interval([1.0, 3.0]) == pytest.approx((2 - 12.706205, 2 + 12.706205), rel=1e-6)
    values = [0.5, -0.2, 0.1, 0.4, 0.7]
    half = 2.776445 * np.std(values, ddof=1) / np.sqrt(5)
    assert report.mean_interval(values) == pytest.approx((np.mean(values) - half, np.mean(values) + half), rel=1e-6)
    assert report.mean_interval([0.3]) is None and report.mean_interval([]) is None


def test_paired_deltas_match_numpy(tmp_path):
    rows, truth = _fake_runs(tmp_path)
    (entry,) = report.paired_deltas(rows, "splatfacto")
    assert entry["method"] == "kc-splatfacto" and entry["seeds"] == [0, 1, 2]
    psnr = [truth[("kc-splatfacto", s, 300)][0] - truth[("splatfacto", s, 300)][0] for s in range(3)]
    ssim = [100 * (truth[("kc-splatfacto", s, 300)][1] / truth[("splatfacto", s, 300)][1] - 1) for s in range(3)]
    np.testing.assert_allclose(entry["psnr_db"], psnr, rtol=1e-12)
    np.testing.assert_allclose(entry["ssim_pct"], ssim, rtol=1e-9)
    assert entry["psnr_db_mean"] == pytest.approx(np.mean(psnr), rel=1e-12)
    assert entry["lpips_pct_mean"] is None and entry["lpips_pct_interval"] is None
    # 95 % t interval over 3 seeds: t_{0.975, 2} = 4.302653 (printed t tables), sample std
    half = 4.302653 * np.std(psnr, ddof=1) / np.sqrt(3)
    assert entry["psnr_db_interval"] == pytest.approx((np.mean(psnr) - half, np.mean(psnr) + half), rel=1e-6)
    table = report.markdown_paired_table([entry], "splatfacto")
    assert f"[{np.mean(psnr) - half:+.2f}, {np.mean(psnr) + half:+.2f}]" in table
    assert f"{np.mean(psnr):+.2f}" in table and f"{psnr[1]:+.2f}" in table
    paths = report.write_report(rows, tmp_path / "out", baseline="splatfacto")
    assert "Per-seed differences" in paths["table"].read_text()


def test_pooled_deltas_match_scipy_t_intervals():
    """The all-pairs estimate is a one-sample t interval over every pair (scipy's ttest_1samp); with two scenes the
    per-scene estimate (m1 + m2) / 2 has half the Welch interval of scipy's ttest_ind(a, -b) (whose difference of
    means is m1 + m2, with the same standard error and Welch-Satterthwaite degrees of freedom)."""
    from scipy import stats

    from kc_splatfacto.analysis.report import pooled_deltas

    rng = np.random.default_rng(3)
    a, b = rng.normal(0.4, 0.3, size=8), rng.normal(-0.2, 0.9, size=5)  # unequal spreads and sizes
    paired = [{"method": "kc", "scene": "one", "seeds": list(range(8)), "psnr_db": a.tolist()},
              {"method": "kc", "scene": "two", "seeds": list(range(5)), "psnr_db": b.tolist()}]
    (pooled,) = pooled_deltas(paired)
    assert pooled["num_pairs"] == 13 and pooled["scenes"] == ["one", "two"]

    both = np.concatenate([a, b])
    assert pooled["psnr_db_all_pairs"] == pytest.approx(both.mean(), abs=1e-12)
    low, high = stats.ttest_1samp(both, 0.0).confidence_interval(0.95)
    assert pooled["psnr_db_all_pairs_interval"] == pytest.approx((low, high), abs=1e-10)

    assert pooled["psnr_db_per_scene"] == pytest.approx((a.mean() + b.mean()) / 2, abs=1e-12)
    low, high = stats.ttest_ind(a, -b, equal_var=False).confidence_interval(0.95)
    assert pooled["psnr_db_per_scene_interval"] == pytest.approx((low / 2, high / 2), abs=1e-10)
    assert pooled["psnr_db_scene_means"] == pytest.approx([a.mean(), b.mean()], abs=1e-12)
    assert "ssim_pct_all_pairs" not in pooled  # a metric no entry has is left out, not reported as zero


def test_pooled_deltas_need_two_pairs_per_scene_for_the_per_scene_interval():
    from kc_splatfacto.analysis.report import pooled_deltas

    paired = [{"method": "kc", "scene": "one", "seeds": [0, 1], "psnr_db": [0.1, 0.3]},
              {"method": "kc", "scene": "two", "seeds": [0], "psnr_db": [0.5]}]
    (pooled,) = pooled_deltas(paired)
    assert pooled["psnr_db_per_scene"] == pytest.approx(0.35)
    assert pooled["psnr_db_per_scene_interval"] is None  # one pair has no within-scene variance
    assert pooled["psnr_db_all_pairs"] == pytest.approx(0.3)


def _timed_log(startup_s: float, startup_cpu_s: float) -> list[dict]:
    """A run logging a train record every 10 steps and evaluations at steps 1 and 50, at 0.02 s (0.03 CPU s) per
    step, its first step also holding ``startup_s`` of one-time work."""
    records = []
    for step in (1, *range(10, 101, 10)):
        clocks = {"train_s": 0.02 * step + startup_s, "train_cpu_s": 0.03 * step + startup_cpu_s,
                  "elapsed_s": 0.025 * step + startup_s}
        records.append({"kind": "train", "step": step, **clocks})
        if step in (1, 50):
            records.append({"kind": "eval", "step": step, "psnr": 20.0, **clocks})
    return records


def test_clocks_leave_out_the_first_steps_start_up():
    """A 110 s start-up in step 1 (kernel compilation) is taken off every clock: the rows equal those of the same
    run without it, and step s costs s times the per-step rate."""
    plain = report.eval_rows(_timed_log(0.0, 0.0), "s", "m", 0)
    compiled = report.eval_rows(_timed_log(110.0, 104.0), "s", "m", 0)
    assert [r["step"] for r in compiled] == [1, 50]
    for a, b in zip(plain, compiled):
        for key in ("train_s", "train_cpu_s", "elapsed_s"):
            assert b[key] == pytest.approx(a[key], abs=1e-9)
    assert compiled[1]["train_s"] == pytest.approx(0.02 * 50) and compiled[1]["train_cpu_s"] == pytest.approx(0.03 * 50)
    assert report.clock_offsets(_timed_log(110.0, 104.0))["train_cpu_s"] == pytest.approx(104.0)
    assert report.clock_offsets([{"kind": "eval", "step": 1, "train_s": 5.0}])["train_s"] == 0.0  # nothing to compare


@pytest.mark.filterwarnings("error::RuntimeWarning")
def test_also_against_pairs_the_third_arm_with_the_second(tmp_path):
    """A three-arm study's report against a second reference: low-pass minus kc at each (scene, seed), by hand, and
    pooled as scipy's one-sample t interval over the pairs; the baseline is not paired with the second reference.
    SSIM is the same in every run: its per-scene interval is the point 0, without a 0/0 warning (issue 68)."""
    from scipy import stats

    rng = np.random.default_rng(11)
    psnr = {(scene, method, seed): 25 + rng.normal(0, 1) for scene in ("a", "b") for method in
            ("splatfacto", "kc-splatfacto", "splatfacto-lowpass") for seed in range(3)}
    rows = [{"scene": scene, "method": method, "seed": seed, "step": 100, "elapsed_s": 1.0, "train_s": 1.0,
             "psnr": value, "ssim": 0.8, "lpips": None, "lpips_vgg": None}
            for (scene, method, seed), value in psnr.items()]
    paths = report.write_report(rows, tmp_path / "out", baseline="splatfacto", also_against=["kc-splatfacto"])
    saved = json.loads(paths["pooled"].read_text())
    assert [e["method"] for e in saved["paired"]] == ["kc-splatfacto", "splatfacto-lowpass"] * 2  # as before
    against = saved["also_against"]["kc-splatfacto"]
    assert [(e["scene"], e["method"]) for e in against["paired"]] == [("a", "splatfacto-lowpass"),
                                                                      ("b", "splatfacto-lowpass")]
    by_hand = [psnr[(scene, "splatfacto-lowpass", s)] - psnr[(scene, "kc-splatfacto", s)]
               for scene in ("a", "b") for s in range(3)]
    np.testing.assert_allclose([v for e in against["paired"] for v in e["psnr_db"]], by_hand, rtol=1e-12)
    (pooled,) = against["pooled"]
    assert pooled["num_pairs"] == 6
    assert pooled["psnr_db_all_pairs_interval"] == pytest.approx(
        stats.ttest_1samp(by_hand, 0.0).confidence_interval(0.95), abs=1e-10)
    assert pooled["ssim_pct_per_scene_interval"] == pooled["ssim_pct_all_pairs_interval"] == [0.0, 0.0]
    table = paths["table"].read_text()
    assert "Per-seed differences to `kc-splatfacto`" in table and "differences to `kc-splatfacto` at the same seed" in table
    low, high = pooled["psnr_db_all_pairs_interval"]
    assert f"{np.mean(by_hand):+.2f} [{low:+.2f}, {high:+.2f}]" in table
    # without it, the report is as it was
    plain = report.write_report(rows, tmp_path / "plain", baseline="splatfacto")
    assert "also_against" not in json.loads(plain["pooled"].read_text())
    assert "`kc-splatfacto`" not in plain["table"].read_text()
