"""The episode worker's bookkeeping that needs no env or backbone (fakes stand in for the env)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from workers.actor import episode_failure


def fake_env(success: bool, steps: int, **extra) -> SimpleNamespace:
    return SimpleNamespace(success=success, steps=steps, **extra)


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        (fake_env(True, 40), (None, None)),
        (fake_env(False, 120), ("timeout", "no success within 120 steps")),
        (fake_env(False, 30), ("ended", "the env ended the episode at step 30")),
        (
            fake_env(False, 57, failure_cause="wrong_order", failure_reason="red before blue"),
            ("wrong_order", "red before blue"),
        ),
        # an env that has the attribute but did not end the episode early: a timeout
        (fake_env(False, 120, failure_cause=None, failure_reason=None), ("timeout", None)),
        # a success is never a failure, whatever the env says
        (fake_env(True, 99, failure_cause="wrong_order"), (None, None)),
    ],
)
def test_episode_failure(env, expected) -> None:
    got = episode_failure(env, max_steps=120)
    assert got["failure"] == expected[0]
    if expected[1] is not None:
        assert got["failure_detail"] == expected[1]
