"""Runs with a shared policy service (executor.policy=shared): the same tables as in-actor for a
row-wise fake and, for a real network (the tiny VLA), the same tables run to run whatever the
arrival of requests, and as in-actor on the same forward shape; a policy actor that dies is
restarted and its requests retried; refusals before any work."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import pandas as pd
import pytest

from pipeline.execution.cluster import check_capacity
from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import RunStore
from tests.pipeline.execution.test_runner import _episodes, _steps

CONF = Path(__file__).resolve().parents[3] / "conf"
SHARED = ["executor.policy=shared", "executor.cpus_per_worker=0.5", "executor.policy_cpus=1"]


@pytest.mark.slow
def test_shared_policy_gives_the_same_tables_as_in_actor(tmp_path, ray_local) -> None:
    base = ["tracking.enabled=false", "executor.kind=ray"]
    in_actor = execute(plan_run(load_config(CONF / "smoke.yaml", base), tmp_path / "in_actor"))
    cfg = load_config(
        CONF / "smoke.yaml",
        [*base, *SHARED, "executor.batch_wait_ms=20", "executor.envs_per_worker=3"],
    )
    shared = execute(plan_run(cfg, tmp_path / "shared"))
    assert in_actor.stored == shared.stored == 12 and shared.errors == 0
    # actions, E_img, success: everything but timing and worker columns, and the numerical path
    # (the closed-form fake's rows give the same floats on any forward shape)
    a, b = _episodes(tmp_path / "in_actor"), _episodes(tmp_path / "shared")
    assert set(a.numerics) == {"request threads=1"} and set(b.numerics) == {"rows=96 threads=1"}
    pd.testing.assert_frame_equal(a.drop(columns="numerics"), b.drop(columns="numerics"))
    pd.testing.assert_frame_equal(_steps(tmp_path / "in_actor"), _steps(tmp_path / "shared"))
    assert any(w.startswith("policy ") for w in shared.workers)
    assert cfg.fingerprint() == load_config(CONF / "smoke.yaml", base).fingerprint()


@pytest.mark.slow
def test_a_policy_actor_that_dies_is_restarted_and_its_requests_retried(tmp_path, ray_local):
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "tracking.enabled=false",
            *SHARED,
            "backbone.kind=tests.doubles.backbones:FaultyMarkerBackbone",
            "backbone.params.exit_on_call=5",
            f"backbone.params.once_dir={tmp_path / 'once'}",
        ],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert (tmp_path / "once" / "backbone_exit-5").exists()  # it did die
    assert summary.stored == 12 and summary.errors == 0
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert eps.error.isna().all() and len(eps) == 12 and (eps.attempt == 1).all()
    steps = RunStore(tmp_path / "run").steps().to_pandas()
    keys = ["cell_id", "task_id", "episode_index", "inference_index"]
    assert not steps.duplicated(keys).any()


@pytest.mark.parametrize(
    ("overrides", "pattern"),
    [
        (["executor.policy=shared", "executor.kind=inline"], "executor.policy=shared runs"),
        (["executor.policy=shared", "executor.max_batch=0"], "max_batch"),
        (["executor.policy=sharded"], "executor.policy"),
        (["executor.policy=shared", "executor.policy_actors=4"], "needs 6 CPUs"),
        (["executor.envs_per_worker=2"], "executor.envs_per_worker applies to policy=shared"),
        (["executor.batching=dynamic"], "executor.batching applies to policy=shared only"),
        (
            ["executor.policy=shared", "executor.batching=dynamic", "executor.forward_rows=12"],
            "batching=dynamic and forward_rows=12 disagree",
        ),
        (["executor.forward_rows=0"], "forward_rows"),
        (["executor.policy=shared", "executor.policy_transport=grpc"], "policy_transport"),
    ],
)
def test_bad_policy_settings_are_refused_before_work(tmp_path, overrides, pattern) -> None:
    with pytest.raises(ConfigError, match=pattern):
        plan_run(load_config(CONF / "smoke.yaml", overrides), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_more_policy_actors_than_gpus_is_refused_with_what_the_cluster_has() -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        ["executor.policy=shared", "executor.policy_actors=3", "executor.gpus_per_worker=1"],
    )
    nodes = [{"CPU": 16.0, "GPU": 2.0, "_id": "a"}, {"CPU": 8.0, "_id": "b"}]
    with pytest.raises(ConfigError, match=r"executor.policy_actors=3 .* need GPU 3.*GPU 2"):
        check_capacity(cfg.executor, nodes)
    ok = load_config(
        CONF / "smoke.yaml",
        ["executor.policy=shared", "executor.policy_actors=2", "executor.gpus_per_worker=1",
         "executor.workers=20"],
    )  # fmt: skip
    check_capacity(ok.executor, nodes)  # 2 GPU actors; 20 episode actors on the 22 CPUs left
    too_many = ok.model_copy(update={"executor": ok.executor.model_copy(update={"workers": 23})})
    with pytest.raises(ConfigError, match="after the policy actors"):
        check_capacity(too_many.executor, nodes)


@pytest.mark.slow
def test_a_policy_actor_out_of_device_memory_splits_and_loses_nothing(
    tmp_path, ray_local, fault_log, caplog
):
    """The policy actor's device holds 4 rows (a FAKE backbone raising torch's out-of-memory
    error above that): forwards of many requests x 3 IDR rows are halved until they fit; the
    episode and step tables equal an in-actor run's, with no error row."""
    base = ["tracking.enabled=false", "executor.kind=ray"]
    in_actor = execute(plan_run(load_config(CONF / "smoke.yaml", base), tmp_path / "in_actor"))
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            *base,
            *SHARED,
            "executor.batching=dynamic",  # a fixed shape is never split (it would change)
            "executor.batch_wait_ms=50",
            "executor.envs_per_worker=3",
            "backbone.kind=tests.doubles.backbones:SmallDeviceMarkerBackbone",
            "backbone.params.max_rows=4",
        ],
    )
    with caplog.at_level(logging.INFO):
        shared = execute(plan_run(cfg, tmp_path / "shared"))
    assert shared.stored == in_actor.stored == 12 and shared.errors == 0
    # the double's entry point vs fake_marker, the path: everything else equal
    name = ["backbone", "numerics"]
    pd.testing.assert_frame_equal(
        _episodes(tmp_path / "in_actor").drop(columns=name),
        _episodes(tmp_path / "shared").drop(columns=name),
    )
    pd.testing.assert_frame_equal(_steps(tmp_path / "in_actor"), _steps(tmp_path / "shared"))
    log = caplog.text
    splits = [int(m) for m in re.findall(r"(\d+) forwards split for lack of device memory", log)]
    assert splits and sum(splits) > 0, "no forward was split: the fault was not injected"
    fault_log.record(
        "a policy actor's forward out of device memory (shared policy service)",
        "FAKE backbone raising torch.OutOfMemoryError above 4 rows; 3 episodes per worker batched",
        "the forward is halved until it fits, the size that fit is remembered; only a request "
        "that fails alone is an error row; tables equal an in-actor run's",
        {
            "stored": shared.stored,
            "errors": shared.errors,
            "forwards_split": sum(splits),
            "tables_equal_in_actor": True,
        },
    )


def test_resuming_on_another_numerical_path_is_refused(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", "executor.kind=inline"])
    execute(plan_run(cfg, tmp_path / "run"))
    other = load_config(
        CONF / "smoke.yaml",
        ["tracking.enabled=false", "executor.kind=inline", "executor.forward_rows=6"],
    )
    with pytest.raises(ConfigError, match=r"'request threads=1'.*'rows=6 threads=1'.*--allow-num"):
        plan_run(other, tmp_path / "run")
    plan = plan_run(other, tmp_path / "run", allow_numerics_change=True)
    assert plan.numerics == "rows=6 threads=1"


def test_a_local_ray_is_started_with_whole_cpus(monkeypatch) -> None:
    """1 episode actor x 0.5 CPU + a policy actor's 1 CPU: Ray refuses 1.5 CPUs, so 2."""
    import pipeline.execution.cluster as cluster

    started = {}
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setattr(cluster, "init_ray", lambda a, n, resources=None: started.update(n=n))
    monkeypatch.setattr(cluster, "alive_nodes", lambda: [{"CPU": 2.0, "_id": "a"}])
    cfg = load_config(CONF / "smoke.yaml", [*SHARED, "executor.workers=1"])
    cluster.connect(cfg.executor)
    assert started["n"] == 2
