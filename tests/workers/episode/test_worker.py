"""The episode worker's bookkeeping that needs no env or backbone (fakes stand in for the env)."""

from __future__ import annotations

from pathlib import Path

import pytest

from workers.envs.base import EpisodeInfo, EpisodeStatus
from workers.episode.worker import episode_failure

CONF = Path(__file__).resolve().parents[3] / "conf"


def last_status(success: bool, steps: int, **info) -> EpisodeStatus:
    """The last status of an episode (the name kept from when status was read off the env)."""
    return EpisodeStatus("t", "go", steps, success, True, int(success), EpisodeInfo(**info))


@pytest.mark.parametrize(
    ("env", "expected"),
    [
        (last_status(True, 40), (None, None)),
        (last_status(False, 120), ("timeout", "no success within 120 steps")),
        (last_status(False, 30), ("ended", "the env ended the episode at step 30")),
        (
            last_status(False, 57, failure_cause="wrong_order", failure_reason="red before blue"),
            ("wrong_order", "red before blue"),
        ),
        # an env that has the attribute but did not end the episode early: a timeout
        (last_status(False, 120, failure_cause=None, failure_reason=None), ("timeout", None)),
        # a success is never a failure, whatever the env says
        (last_status(True, 99, failure_cause="wrong_order"), (None, None)),
    ],
)
def test_episode_failure(env, expected) -> None:
    got = episode_failure(env, max_steps=120)
    assert got["failure"] == expected[0]
    if expected[1] is not None:
        assert got["failure_detail"] == expected[1]


def _worker(replan_steps: int = 3, **backbone: object):
    from workers.episode.rows import WorkerSpec
    from workers.episode.worker import EpisodeWorker

    params = {"chunk_len": 4, "noise_std": 0.05, **backbone}
    return EpisodeWorker(WorkerSpec("fake_marker", params, "fake_marker", {}, replan_steps))


def _spec(task_id: str, episode: int, mode: str = "E"):
    from idr_core.interventions import InterventionConfig
    from idr_core.refiner import RefinerConfig

    from workers.envs.factory import suite_tasks
    from workers.episode.rows import EpisodeSpec

    (task,) = [t for t in suite_tasks("fake_marker", {}) if t.task_id == task_id]
    return EpisodeSpec(
        "r", mode, RefinerConfig(mode=mode), InterventionConfig(), task, episode, 0, "fake"
    )


@pytest.mark.parametrize(("task_id", "episode"), [("reach", 0), ("reach_chain", 1)])
def test_rollout_executes_replan_steps_of_each_chunk(task_id, episode) -> None:
    """One inference every replan_steps control steps; the env gets exactly the first
    replan_steps actions of each refined chunk (fewer at the end); the rows say so."""
    import numpy as np

    w = _worker(replan_steps=3)
    chunks, sent = [], []
    infer, step = w.policy.infer, w.env.step
    w.policy.infer = lambda obs, seed, *cell: chunks.append(out := infer(obs, seed, *cell)) or out
    w.env.step = lambda a: sent.append(np.array(a)) or step(a)
    try:
        res = w.run_episode(_spec(task_id, episode))
    finally:
        w.close()
    ep, steps = res.episode, res.steps
    assert ep.error is None and ep.steps == len(sent) > 3
    assert [s.step for s in steps] == list(range(0, ep.steps, 3))
    assert [s.inference_index for s in steps] == list(range(len(chunks)))
    expected = np.concatenate([c.action[0, :3].numpy() for c in chunks])[: ep.steps]
    np.testing.assert_array_equal(np.stack(sent), expected)
    for s, c in zip(steps, chunks, strict=True):
        np.testing.assert_allclose(s.action_final, c.action[0, 0].numpy(), rtol=1e-6)
        np.testing.assert_allclose(s.action_base, c.a_base[0, 0].numpy(), rtol=1e-6)
    assert ep.sim_seconds == pytest.approx(ep.steps / 10.0)  # FakeMarkerEnv: 10 Hz
    if ep.success:
        assert ep.success_step is not None and ep.success_step <= ep.steps
    assert ep.gate_rate == pytest.approx(np.mean([s.gate for s in steps]))
    assert ep.crn is True  # the fake head takes noise: the three passes shared one draw


def test_a_user_env_with_status_properties_runs_as_the_record_env_does() -> None:
    """An env named by entry point that keeps status as properties (written before the
    record) gives the same episode rows, through the adapter."""
    from workers.episode.rows import WorkerSpec
    from workers.episode.worker import EpisodeWorker

    rows = []
    for entry in ("fake_marker", "tests.doubles.envs:PropertyMarkerEnv"):
        params = {"chunk_len": 4, "noise_std": 0.05}
        w = EpisodeWorker(WorkerSpec("fake_marker", params, entry, {}, 3))
        try:
            res = [w.run_episode(_spec(t, e)) for t, e in (("reach", 0), ("reach_chain", 1))]
        finally:
            w.close()
        keep = ("success", "steps", "subtasks_done", "failure", "instruction", "init_state_id")
        rows.append([({k: getattr(r.episode, k) for k in keep}, len(r.steps)) for r in res])
        assert all(r.episode.error is None for r in res)
    assert rows[0] == rows[1]


def test_cells_see_common_random_numbers(tmp_path) -> None:
    """Paired cells: at the same task, episode and inference the baseline, diagnose and E
    cells draw the same noise, so diagnose (which executes a_base) retraces the baseline
    exactly and E's first base action equals the baseline's."""
    from pipeline.execution.runner import plan_run, run_episodes
    from pipeline.planning.config import load_config
    from pipeline.results.store import RunStore

    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "tracking.enabled=false",
            "executor.kind=inline",
            "grid=[{mode: [baseline, diagnose, E]}]",
            "episodes_per_task=2",
        ],
    )
    plan = plan_run(cfg, tmp_path / "run")
    run_episodes(plan)
    steps = RunStore(plan.run_dir).steps().to_pandas()
    by_cell = {
        c: g.set_index(["task_id", "episode_index", "inference_index"]).sort_index()
        for c, g in steps.groupby("cell_id")
    }
    base, diag, e = (
        {k: list(v) for k, v in by_cell[c].action_base.items()}
        for c in ("baseline", "diagnose", "E")
    )
    assert len(base) > 0 and base == diag
    firsts = [k for k in base if k[2] == 0]
    assert len(firsts) == 4 and all(e[k] == base[k] for k in firsts)
    # not trivially equal: the noise differs from one inference to the next
    assert base[firsts[0]] != base[(*firsts[0][:2], 1)]
