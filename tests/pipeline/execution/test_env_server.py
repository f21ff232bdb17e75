"""Runs with the env in an env server (env.python): the same tables as in-process, a server
that dies under an episode costs a restart (not the episode), nothing is left behind, and a
bad interpreter or a missing checkout is refused before any work."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import RunStore
from tests.pipeline.execution.test_runner import _episodes, _steps

CONF = Path(__file__).resolve().parents[3] / "conf"
SERVER = f"env.python={sys.executable}"


def _descends_from_this_process(pid: int) -> bool:
    """Whether this test process is an ancestor of ``pid`` (its Ray's actors and their env
    servers are; another pytest worker's are not)."""
    me = os.getpid()
    while pid > 1:
        if pid == me:
            return True
        try:
            pid = _parent(pid)
        except OSError:
            return False
    return False


def _servers() -> set[int]:
    """pids of the env servers this test process started, directly or through its actors
    (other pytest workers run env servers of their own at the same time)."""
    found = set()
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                cmd = (d / "cmdline").read_bytes()
            except OSError:
                continue
            if b"workers.envs.server.serve" in cmd and _descends_from_this_process(int(d.name)):
                found.add(int(d.name))
    return found


def _wait_gone(pids: set[int], within_s: float = 10) -> set[int]:
    deadline = time.monotonic() + within_s
    while (left := pids & _servers()) and time.monotonic() < deadline:
        time.sleep(0.1)
    return left


def test_same_tables_in_process_and_in_an_env_server(tmp_path) -> None:
    base = ["executor.kind=inline", "tracking.enabled=false"]
    cfg_local = load_config(CONF / "smoke.yaml", base)
    cfg_remote = load_config(CONF / "smoke.yaml", [*base, SERVER])
    # where the simulator runs does not change results: the same fingerprint (resume allowed)
    assert cfg_local.fingerprint() == cfg_remote.fingerprint()
    before = _servers()
    s1 = execute(plan_run(cfg_local, tmp_path / "local"))
    s2 = execute(plan_run(cfg_remote, tmp_path / "remote"))
    assert s1.stored == s2.stored == 12 and s1.errors == s2.errors == 0
    pd.testing.assert_frame_equal(_episodes(tmp_path / "local"), _episodes(tmp_path / "remote"))
    pd.testing.assert_frame_equal(_steps(tmp_path / "local"), _steps(tmp_path / "remote"))
    meta = json.loads((tmp_path / "remote" / "run.json").read_text())
    assert meta["env_server"]["python"] == sys.version.split()[0]
    assert not _wait_gone(_servers() - before)


def test_a_server_dying_under_an_episode_is_restarted_and_the_episode_run_again(tmp_path):
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "tracking.enabled=false",
            "env.tasks=[reach_chain]",
            "episodes_per_task=2",
            "grid=[{mode: [E]}]",
            "env.suite=tests.doubles.envs:ServerFaultEnv",
            "env.params.exit_at_step=6",  # mid-chunk, after steps rows were made
            f"env.params.once_dir={tmp_path / 'once'}",
            SERVER,
        ],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert sorted(p.name for p in (tmp_path / "once").iterdir()) == [
        "server_exit-0",
        "server_exit-1",
    ]  # the server died under both episodes
    assert summary.stored == 2 and summary.errors == 0
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert eps.error.isna().all() and (eps.attempt == 1).all()  # not charged an attempt
    steps = RunStore(tmp_path / "run").steps().to_pandas()
    for _, g in steps.groupby("episode_index"):  # the rerun's rows only, once each
        assert list(g.inference_index) == list(range(len(g)))


@pytest.mark.slow
def test_ray_actors_start_servers_and_none_outlive_them(tmp_path, ray_local) -> None:
    from workers.envs.server.client import ServerSpec
    from workers.episode.rows import WorkerSpec
    from workers.episode.worker import remote_worker_class

    before = _servers()
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", SERVER])
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert summary.stored == 12 and summary.errors == 0 and len(summary.workers) == 2
    assert not _wait_gone(_servers() - before), "env servers outlived the run"

    # an actor killed outright (no close): its server goes with it
    spec = WorkerSpec("fake_marker", {}, "fake_marker", {}, 4, None, ServerSpec(sys.executable))
    actor = remote_worker_class(1, 0).remote(spec)
    actor_pid = int(ray_local.get(actor.ping.remote()).rsplit(":", 1)[1])
    mine = {p for p in _servers() - before if _parent(p) == actor_pid}
    assert len(mine) == 1
    ray_local.kill(actor)
    assert not _wait_gone(mine), "the env server outlived its killed actor"


def _parent(pid: int) -> int:
    stat = Path(f"/proc/{pid}/stat").read_text()
    return int(stat.rsplit(")", 1)[1].split()[1])


@pytest.mark.parametrize(
    ("overrides", "pattern"),
    [
        (["env.python=/nonexistent/bin/python"], r"env.python=/nonexistent/bin/python: no such"),
        ([f"env.python={os.devnull}"], "not an executable file"),
        (
            [
                SERVER,
                "env.suite=tests.doubles.envs:ServerFaultEnv",
                "env.params.missing_checkout=/nonexistent/checkout",
            ],
            r"env.params.missing_checkout=/nonexistent/checkout: no such checkout",
        ),
        (  # the same check where the env runs in-process
            [
                "env.suite=tests.doubles.envs:ServerFaultEnv",
                "env.params.missing_checkout=/nonexistent/checkout",
            ],
            r"env.params.missing_checkout=/nonexistent/checkout: no such checkout",
        ),
    ],
)
def test_where_the_env_runs_is_checked_before_any_work(tmp_path, overrides, pattern) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", *overrides])
    with pytest.raises(ConfigError, match=pattern):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
