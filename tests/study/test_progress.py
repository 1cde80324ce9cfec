"""kc-bench's progress line: counts and an ETA that a resumed study has from its first line (the reused runs'
recorded wall times) and that the runs trained here replace."""

import io

from kc_splatfacto.study.runners import Progress, recorded_wall


def _reused(*elapsed: float) -> dict:
    return {"status": "reused", "wall_s": 0.01,
            "records": [{"kind": "eval", "step": 10 * (i + 1), "elapsed_s": e} for i, e in enumerate(elapsed)]}


def test_a_fresh_study_has_no_eta_until_a_run_trained():
    progress = Progress(total=4, slots=2, stream=io.StringIO())
    progress.started()
    assert progress.line() == "[kc-bench] 0/4 finished, 1 running, 3 queued; ETA ?"
    progress.ended({"status": "trained", "wall_s": 600.0, "records": []})
    # 3 runs left at 600 s each, two at once
    assert progress.line() == "[kc-bench] 1/4 finished, 0 running, 3 queued; ETA 15m00s"


def test_a_resumed_study_estimates_from_the_reused_runs_until_one_trains_here():
    progress = Progress(total=6, slots=2, stream=io.StringIO())
    for result in (_reused(5.0, 600.0), _reused(40.0, 1200.0)):  # each run's last elapsed_s: its whole wall time
        progress.started()
        progress.ended(result)
    # 4 left at the mean 900 s, two at once
    assert progress.eta() == 1800.0
    assert progress.line() == ("[kc-bench] 2/6 finished, 0 running, 4 queued; "
                               "ETA 30m00s (from the reused runs' recorded times)")
    progress.started()
    progress.ended({"status": "resumed", "wall_s": 300.0, "records": []})
    # the runs trained here replace the guess: 3 left at 300 s
    assert progress.line() == "[kc-bench] 3/6 finished, 0 running, 3 queued; ETA 7m30s"


def test_runs_still_to_reuse_are_not_left_to_train():
    # a resumed study of 6: 4 finished in their folders, 2 of them read so far; 2 runs are left to train, not 4
    progress = Progress(total=6, slots=2, stream=io.StringIO(), to_reuse=4)
    for result in (_reused(600.0), _reused(1200.0)):
        progress.started()
        progress.ended(result)
    assert progress.eta() == 900.0  # 2 left at the mean 900 s, two at once
    for result in (_reused(300.0), _reused(300.0)):  # the other two read: still 2 left, now at the mean 600 s
        progress.ended(result)
    assert progress.eta() == 600.0
    progress.ended({"status": "trained", "wall_s": 100.0, "records": []})
    assert progress.eta() == 50.0  # 1 left at the 100 s trained here, on one of two slots


def test_failures_count_and_a_finished_study_needs_no_time():
    progress = Progress(total=2, slots=1, stream=io.StringIO())
    progress.ended({"status": "failed", "wall_s": 3.0, "records": []})
    progress.ended(_reused(50.0))
    assert progress.eta() == 0.0
    assert progress.line() == "[kc-bench] 2/2 finished (1 failed), 0 running, 0 queued; ETA 0m00s"


def test_recorded_wall_is_the_last_elapsed_time_and_none_without_one():
    records = [{"kind": "eval", "step": 1, "elapsed_s": 1.5}, {"kind": "train", "step": 2, "elapsed_s": 9.0},
               {"kind": "note", "step": 2}]
    assert recorded_wall(records) == 9.0
    assert recorded_wall([{"kind": "note", "step": 1}]) is None
    progress = Progress(total=3, slots=1, stream=io.StringIO())
    progress.ended({"status": "reused", "wall_s": 0.0, "records": []})  # nothing recorded: no guess from it
    assert progress.eta() is None
