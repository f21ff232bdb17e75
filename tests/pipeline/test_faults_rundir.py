"""Driver mistakes around the run dir: a config that would blow up, a plan too large to build,
the run dir deleted mid-run, a lost run.json, unreadable Parquet files. Each is one clear error
or a recovery, and nothing is lost or stored twice."""

from __future__ import annotations

import shutil
import tracemalloc
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.errors import RunDirLostError
from pipeline.execution import claim
from pipeline.execution.runner import execute, plan_run, run_episodes
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import RunStore
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "conf" / "smoke.yaml"
BASE = ["tracking.enabled=false", "executor.kind=inline"]
KEYS = {(c, t, i) for c in ("baseline", "E") for t in ("reach", "reach_chain") for i in range(3)}

BOMB = """name: bomb
backbone: {kind: fake_marker}
env: {suite: fake_marker}
a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]
""" + "".join(
    f"{n}: &{n} [{', '.join([f'*{p}'] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)


def test_an_alias_bomb_is_refused_while_parsing(tmp_path, fault_log) -> None:
    """A 1 KB file of nested aliases (9^9 strings once expanded) is refused before anything
    copies it: one error naming the alias, a few MB of memory at most."""
    config = tmp_path / "bomb.yaml"
    config.write_text(BOMB)
    assert len(BOMB) < 1024
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match=r"YAML alias \*a at line 5"):
            load_config(config)
        with pytest.raises(ConfigError, match=r"YAML alias \*x"):
            load_config(SMOKE, ["backbone.params={a: &x [1, 2], b: *x}"])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20
    fault_log.record(
        "YAML alias bomb",
        "a 1 KB config of nested aliases (9^9 strings expanded); an alias in an override",
        "refused while parsing, before any copy: one error naming the alias",
        {"peak_memory_mb": round(peak / 2**20, 2), "config_bytes": len(BOMB)},
    )


def test_a_plan_too_large_is_refused_before_it_is_built(tmp_path, fault_log) -> None:
    cfg = load_config(SMOKE, [*BASE, "episodes_per_task=1000000000"])
    plan_run(load_config(SMOKE, BASE), tmp_path / "warm")  # imports done before measuring
    tracemalloc.start()
    try:
        with pytest.raises(ConfigError, match=r"max_episodes: the plan has 4000000000 episodes"):
            plan_run(cfg, tmp_path / "run")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20 * 2**20 and not (tmp_path / "run").exists()
    ok = load_config(SMOKE, [*BASE, "max_episodes=12"])
    assert len(plan_run(ok, tmp_path / "ok").all_specs()) == 12  # the limit itself is fine
    with pytest.raises(ConfigError, match="max_episodes"):
        plan_run(load_config(SMOKE, [*BASE, "max_episodes=11"]), tmp_path / "ok")
    assert (
        len(
            plan_run(
                load_config(SMOKE, [*BASE, "max_episodes=11"]), tmp_path / "ok", yes=True
            ).all_specs()
        )
        == 12
    )
    fault_log.record(
        "episodes_per_task=1000000000",
        "a plan of 4e9 episodes",
        "refused before the plan is built (max_episodes, --yes to confirm)",
        {"peak_memory_mb": round(peak / 2**20, 2)},
    )


def test_a_run_dir_deleted_mid_run_stops_the_run(tmp_path, fault_log) -> None:
    plan = plan_run(load_config(SMOKE, [*BASE, "executor.flush_every=1"]), tmp_path / "run")
    claim.write_meta(plan)
    flushed: list[int] = []

    def delete_after_two(batch) -> None:
        flushed.append(len(batch))
        if len(flushed) == 2:
            shutil.rmtree(plan.run_dir)

    with pytest.raises(RunDirLostError, match=r"lost run.json, episodes, steps while this run"):
        run_episodes(plan, RunStore(plan.run_dir), on_flush=delete_after_two)
    assert len(flushed) == 2 and not plan.run_dir.exists()  # nothing recreated
    fault_log.record(
        "run dir deleted mid-run",
        "rm -rf RUN_DIR after 2 batches",
        "the next flush stops the run with one error (exit 1); the dir is not recreated",
        {"batches_before": 2, "dir_recreated": int(plan.run_dir.exists())},
    )


def test_a_run_dir_without_run_json_is_adopted_on_request(tmp_path, fault_log) -> None:
    cfg = load_config(SMOKE, BASE)
    execute(plan_run(cfg, tmp_path / "run"))
    run_id = RunStore(tmp_path / "run").episodes().column("run_id")[0].as_py()
    (tmp_path / "run" / "run.json").unlink()
    with pytest.raises(ConfigError, match=r"has no run.json but holds 12 stored episodes.*--adopt"):
        plan_run(cfg, tmp_path / "run")
    other = load_config(SMOKE, [*BASE, "seed=1"])
    with pytest.raises(ConfigError, match=r"--adopt: .*config.yaml is a different config"):
        plan_run(other, tmp_path / "run", adopt=True)
    plan = plan_run(cfg, tmp_path / "run", adopt=True)
    assert plan.run_id == run_id
    summary = execute(plan)
    assert summary.skipped == 12 and summary.stored == 0
    assert_clean(audit(tmp_path / "run", KEYS))
    fault_log.record(
        "run.json lost",
        "run.json deleted from a finished run dir; run again, then with --adopt",
        "refused with the fix named; --adopt checks config.yaml's fingerprint, keeps the run id, "
        "re-runs nothing",
        {"re_run": summary.stored, "skipped": summary.skipped},
    )


@pytest.mark.parametrize("table", ["episodes", "steps"])
def test_unreadable_batches_are_quarantined_and_rerun(tmp_path, fault_log, table) -> None:
    from pipeline.reporting.markdown import build_report

    out = tmp_path / "run"
    cfg = load_config(SMOKE, BASE)
    execute(plan_run(cfg, out))
    victim = sorted((out / table).rglob("*.parquet"))[1]  # a compacted file: a whole cell
    victim.write_bytes(victim.read_bytes()[:200])  # a copy cut short
    assert "1 unreadable Parquet files skipped here" in build_report(out)
    summary = execute(plan_run(cfg, out))
    assert summary.stored == 6 and summary.skipped == 6  # the quarantined cell ran again
    quarantined = sorted(
        p.relative_to(out).as_posix() for p in (out / "quarantine").rglob("*.parquet")
    )
    assert len(quarantined) == 2 and {p.split("/")[1] for p in quarantined} == {"episodes", "steps"}
    outcome = audit(out, KEYS)
    assert_clean(outcome)
    for f in out.glob("*/cell=*/*.parquet"):
        pq.read_table(f)
    import json

    assert sorted(json.loads((out / "run.json").read_text())["quarantined"]) == quarantined
    steps = RunStore(out, read_only=True).steps().to_pandas()
    per_key = steps.groupby(["cell_id", "task_id", "episode_index"]).inference_index.apply(list)
    assert all(v == list(range(len(v))) for v in per_key)  # each inference once, none lost
    assert len(per_key) == 12
    fault_log.record(
        f"unreadable {table} batch",
        f"a {table} file truncated to 200 bytes after the run; report, then run again",
        "report skips it and says so; the next run moves it and its partner to quarantine/ "
        "(named in run.json) and re-runs their episodes",
        {**outcome, "quarantined_files": len(quarantined)},
    )


def test_resume_refuses_another_checkpoint_content_or_code_version(tmp_path, fault_log) -> None:
    import json
    import os

    ckpt = tmp_path / "ckpt"
    shutil.copytree(ROOT / "checkpoints" / "tiny_vla", ckpt)
    cfg = load_config(
        SMOKE,
        [
            *BASE,
            "backbone.kind=tests.doubles.backbones:CheckpointedMarkerBackbone",
            f"backbone.params.path={ckpt}",
        ],
    )
    execute(plan_run(cfg, tmp_path / "run"))
    meta = json.loads((tmp_path / "run" / "run.json").read_text())
    assert len(meta["checkpoint"]["sha256"]) == 64 and meta["code_version"]
    os.utime(ckpt / "config.json")  # touched, same content: hashed again, same digest
    assert plan_run(cfg, tmp_path / "run").checkpoint["sha256"] == meta["checkpoint"]["sha256"]
    weights = ckpt / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:-1] + b"\x01")  # another content, same size
    with pytest.raises(ConfigError, match=r"another content of the checkpoint .* never mixed"):
        plan_run(cfg, tmp_path / "run")
    shutil.copy(ROOT / "checkpoints" / "tiny_vla" / "model.safetensors", weights)
    meta["code_version"] = "0123abcd-dirty"
    (tmp_path / "run" / "run.json").write_text(json.dumps(meta))
    with pytest.raises(ConfigError, match=r"code version 0123abcd-dirty.*--allow-code-change"):
        plan_run(cfg, tmp_path / "run")
    assert plan_run(cfg, tmp_path / "run", allow_code_change=True).run_id == meta["run_id"]
    fault_log.record(
        "checkpoint or code changed under a run dir",
        "weights rewritten at the same path; run.json of another code version; then resume",
        "refused before any work, naming both digests / versions; --allow-code-change resumes",
        {"refused": 2},
    )
