"""The executor section's shape says what it can do: ``policy`` picks the variant (in_actor
where it is absent), a shared-only key given to an in_actor run is refused with one message
naming it and the fix, overrides switch the variant, and a run's record still reads."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from pipeline.errors import ConfigError
from pipeline.planning.config import config_from_dict, load_config, load_run_record
from pipeline.planning.executor_config import (
    SHARED_ONLY,
    ExecutorBase,
    InActorExecutor,
    SharedExecutor,
)

CONF = Path(__file__).resolve().parents[3] / "conf"
BASE = {"backbone": {"kind": "fake_marker"}, "env": {"suite": "fake_marker"}}


def _refusal(executor: dict) -> str:
    with pytest.raises(ConfigError) as info:
        config_from_dict({**BASE, "executor": executor})
    return str(info.value)


def test_policy_picks_the_variant_and_in_actor_is_the_default() -> None:
    assert isinstance(config_from_dict(BASE).executor, InActorExecutor)
    assert isinstance(
        config_from_dict({**BASE, "executor": {"workers": 3}}).executor, InActorExecutor
    )
    shared = config_from_dict({**BASE, "executor": {"policy": "shared", "max_batch": 4}}).executor
    assert isinstance(shared, SharedExecutor) and shared.max_batch == 4
    # the shared policy's keys are its own: an in_actor run has none to ignore
    assert set(SHARED_ONLY) == set(SharedExecutor.model_fields) - set(ExecutorBase.model_fields)
    assert not set(SHARED_ONLY) & set(InActorExecutor.model_fields)
    assert {"policy_transport", "max_batch", "batch_wait_ms", "policy_connections"} <= set(
        SHARED_ONLY
    )


@pytest.mark.parametrize(
    "key, value",
    [
        ("policy_transport", "socket"),  # the default transport too: in_actor has none
        ("policy_transport", "ray"),
        ("max_batch", 4),
        ("batch_wait_ms", 5),
        ("policy_connections", 5),
        ("envs_per_worker", 2),
        ("batching", "fixed"),
    ],
)
def test_a_shared_key_given_to_an_in_actor_run_is_refused_with_one_message(key, value) -> None:
    for executor in ({key: value}, {"policy": "in_actor", key: value}):
        text = _refusal(executor)
        lines = text.splitlines()[1:]
        assert lines == [
            f"  executor.{key} applies to policy=shared only: set executor.policy=shared or drop it"
        ], text
    both = _refusal({"max_batch": 4, "policy_transport": "ray"})
    assert both.splitlines()[1:] == [
        "  executor.max_batch, executor.policy_transport apply to policy=shared only: set "
        "executor.policy=shared or drop them"
    ]


def test_errors_name_the_key_as_written_without_the_variant_tag() -> None:
    text = _refusal({"policy": "shared", "max_batch": 0})
    assert "  executor.max_batch: Input should be greater than or equal to 1 (got 0)" in text
    assert "shared.max_batch" not in text
    assert "did you mean 'max_batch'?" in _refusal({"policy": "shared", "max_bach": 4})
    assert "did you mean 'workers'?" in _refusal({"wrokers": 4})
    assert "  executor.policy: Input should be one of 'in_actor', 'shared' (got 'sharded')" in (
        _refusal({"policy": "sharded"})
    )


def test_the_socket_bounds_are_refused_on_ray_calls() -> None:
    text = _refusal({"policy": "shared", "policy_transport": "ray", "policy_idle_s": 30})
    assert "executor.policy_idle_s applies to policy_transport=socket only" in text
    ok = {"policy": "shared", "policy_transport": "socket", "policy_idle_s": 30}
    assert config_from_dict({**BASE, "executor": ok}).executor.policy_idle_s == 30


def test_an_override_switches_the_variant(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["executor.policy=shared", "executor.max_batch=4"])
    assert isinstance(cfg.executor, SharedExecutor) and cfg.executor.forward_shape() == 12
    shared_yaml = tmp_path / "shared.yaml"
    data = yaml.safe_load((CONF / "smoke.yaml").read_text())
    shared_yaml.write_text(yaml.safe_dump({**data, "executor": {"policy": "shared"}}))
    back = load_config(shared_yaml, ["executor.policy=in_actor", "executor.workers=1"])
    assert isinstance(back.executor, InActorExecutor) and back.executor.workers == 1
    # a shared run's own setting does not go silently with the switch
    shared_yaml.write_text(
        yaml.safe_dump({**data, "executor": {"policy": "shared", "max_batch": 8}})
    )
    with pytest.raises(ConfigError, match=r"executor\.max_batch applies to policy=shared only"):
        load_config(shared_yaml, ["executor.policy=in_actor"])
    # from Python: a RunConfig's defaults are not settings the switch would have to drop
    from pipeline.api.run import load

    switched = load(
        cfg.model_copy(update={"executor": SharedExecutor()}), ["executor.policy=in_actor"]
    )
    assert isinstance(switched.executor, InActorExecutor)
    assert isinstance(
        load(config_from_dict(BASE), {"executor.policy": "shared"}).executor, SharedExecutor
    )


def test_what_runs_follows_the_variant() -> None:
    in_actor = InActorExecutor(workers=3, cpus_per_worker=2, gpus_per_worker=0.5)
    assert in_actor.forward_shape() is None and in_actor.threads() == 2
    assert in_actor.episodes_per_actor() == 1
    assert in_actor.actor_groups() == [("executor.workers", 3, {"CPU": 2, "GPU": 0.5})]
    shared = SharedExecutor(workers=3, gpus_per_worker=1, policy_cpus=4, envs_per_worker=2)
    assert shared.forward_shape() == 96 and shared.threads() == 4
    assert shared.episodes_per_actor() == 2
    assert shared.actor_groups() == [
        ("executor.policy_actors", 1, {"CPU": 4, "GPU": 1}),
        ("executor.workers", 3, {"CPU": 1, "GPU": 0.0}),  # an episode actor holds no model
    ]
    assert SharedExecutor(batching="dynamic").forward_shape() == "dynamic"


def test_a_run_record_listing_every_executor_key_still_reads(tmp_path) -> None:
    """A run dir's config.yaml may list an in_actor run's executor with every key at its
    default (shared ones included); read as the run's record it loads, as the same config.
    Given to run, the same file is refused: those keys would be ignored."""
    every = {
        **InActorExecutor().model_dump(mode="json"),
        **SharedExecutor().model_dump(mode="json"),
    }
    record = tmp_path / "config.yaml"
    record.write_text(yaml.safe_dump({**BASE, "executor": {**every, "policy": "in_actor"}}))
    cfg = load_run_record(record)
    assert cfg.executor == InActorExecutor()
    with pytest.raises(ConfigError, match="apply to policy=shared only"):
        load_config(record)
    shared = tmp_path / "shared.yaml"
    shared.write_text(yaml.safe_dump({**BASE, "executor": {**every, "max_batch": 4}}))
    assert load_run_record(shared).executor == SharedExecutor(max_batch=4)
