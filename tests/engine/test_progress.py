"""The progress bar of kc_splatfacto/engine/metrics_log.py: tqdm on a terminal, plain lines elsewhere, an ETA that
leaves the compiling first steps out."""

from __future__ import annotations

import io
import math
import re

from kc_splatfacto.engine.metrics_log import ETA_WARMUP_STEPS, ProgressBar, format_duration


class FakeTerminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_a_log_file_gets_a_line_every_n_steps_and_no_redraws():
    stream = io.StringIO()
    bar = ProgressBar(250, enabled=True, stream=stream, line_every=100)
    assert not bar.interactive
    for step in range(1, 251):
        bar.update(step, 0.5, 1000)
    bar.update(250, 0.5, 1000, force=True)  # the trainer's closing update: no second line for step 250
    bar.close()
    lines = stream.getvalue().splitlines()
    assert [int(re.match(r"step (\d+)/250", line).group(1)) for line in lines] == [100, 200, 250]
    assert "\r" not in stream.getvalue() and "1,000 GS" in lines[-1] and "loss 0.5000" in lines[-1]


def test_a_terminal_gets_a_tqdm_bar():
    stream = FakeTerminal()
    bar = ProgressBar(50, enabled=True, stream=stream)
    assert bar.interactive
    for step in range(1, 51):
        bar.update(step, 0.25, 12, force=step == 50)
    bar.close()
    text = stream.getvalue()
    assert "\r" in text and "50/50" in text and "ETA" in text and "12 GS" in text


def test_the_eta_leaves_the_warmup_steps_out():
    """First steps of 10 s each (compilation), then 0.1 s a step: the ETA is the steady rate's, not the mean's."""
    bar = ProgressBar(100, enabled=False)
    now = 0.0
    for step in range(1, ETA_WARMUP_STEPS + 1):
        now += 10.0
        rate, eta = bar.rate_and_eta(step, now)
        assert math.isnan(rate) and math.isinf(eta)  # nothing to measure yet
    for step in range(ETA_WARMUP_STEPS + 1, 21):
        now += 0.1
        rate, eta = bar.rate_and_eta(step, now)
    assert math.isclose(rate, 10.0, rel_tol=1e-9) and math.isclose(eta, (100 - 20) / 10.0, rel_tol=1e-9)


def test_a_resumed_run_counts_its_warmup_from_the_resume_step():
    bar = ProgressBar(1000, start=500, enabled=False)
    assert math.isinf(bar.rate_and_eta(500 + ETA_WARMUP_STEPS - 1, 1.0)[1])
    bar.rate_and_eta(500 + ETA_WARMUP_STEPS, 2.0)
    rate, eta = bar.rate_and_eta(500 + ETA_WARMUP_STEPS + 10, 3.0)
    assert math.isclose(rate, 10.0) and math.isclose(eta, (1000 - 515) / 10.0)


def test_format_duration():
    assert format_duration(75) == "1:15" and format_duration(3723) == "1:02:03" and format_duration(math.inf) == "?"


def test_disabled_writes_nothing():
    stream = FakeTerminal()
    bar = ProgressBar(10, enabled=False, stream=stream)
    bar.update(5, 0.1, 1, force=True)
    bar.close()
    assert stream.getvalue() == ""
