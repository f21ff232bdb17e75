"""The progress line's ETA: measured per task, none before the first episode."""

from __future__ import annotations

import logging

import pytest

from pipeline.execution.progress import EtaModel, Progress


def test_eta_weights_each_task_by_its_own_episode_time() -> None:
    # 10 short episodes (1 s) then 10 long ones (10 s) on 2 slots
    eta = EtaModel({"short": 10, "long": 10}, slots=2)
    assert eta.seconds() is None  # nothing measured yet: no guess
    eta.finished("short", 30.0)  # each slot's first episode pays the worker's start
    assert eta.seconds() == pytest.approx(19 * 30.0 / 2)  # all there is, for now
    eta.finished("short", 30.0)
    for _ in range(8):
        eta.finished("short", 1.0)  # from now on the warm-up ones are left out
    # the long task is unseen: the overall mean stands in for it
    assert eta.seconds() == pytest.approx(10 * 1.0 / 2)
    eta.finished("long", 10.0)
    # 9 long episodes left at 10 s each over 2 slots; a count-based rate would say ~5 s
    assert eta.seconds() == pytest.approx(9 * 10.0 / 2)


def test_eta_of_a_resume_counts_stored_episodes_as_done() -> None:
    eta = EtaModel({"t": 4}, slots=4)
    for _ in range(3):
        eta.skipped("t")
    eta.finished("t", 8.0)
    assert eta.seconds() == 0.0
    # fewer episodes left than slots: they do not run faster than one each
    eta = EtaModel({"t": 3}, slots=8)
    eta.finished("t", 6.0)
    assert eta.seconds() == pytest.approx(6.0)


def test_log_lines_say_when_there_is_no_eta_and_end_once(caplog) -> None:
    caplog.set_level(logging.INFO, logger="idr_eval.progress")
    p = Progress(3, {"t": 3}, slots=1)
    p.update(1, 1, 0)  # an episode stored by an earlier run: nothing timed yet
    p.eta.finished("t", 2.0)
    p.update(3, 2, 0)
    p.update(3, 2, 0)
    lines = [r.getMessage() for r in caplog.records]
    assert lines[0].endswith("eta: after the first episode")
    assert [line for line in lines if line.startswith("episodes 3/3")] == [lines[-1]]
    assert "nan" not in " ".join(lines)


def test_a_resumed_run_rates_success_over_the_episodes_it_finished(caplog) -> None:
    """Episodes an earlier run stored count towards done, not towards the success rate: their
    successes were not counted here."""
    caplog.set_level(logging.INFO, logger="idr_eval.progress")
    p = Progress(10, {"t": 10}, slots=1)
    p.eta.finished("t", 2.0)
    p.update(10, 3, 1, skipped=6)
    (line,) = [r.getMessage() for r in caplog.records]
    assert "success 3/3  errors 1  (6 stored before)" in line
