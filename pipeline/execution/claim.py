"""Whose run dir this is: a new run claims it, the same config resumes it, another config is
refused, a run dir whose run.json was lost is adopted on request; run.json's record of the run
(run id, fingerprint, code version, checkpoint digest, env server, fit, protocol)."""

from __future__ import annotations

import logging
import subprocess
import uuid
from pathlib import Path

from pipeline.errors import RunDirLostError
from pipeline.planning.config import ConfigError, RunConfig, dump_config
from pipeline.planning.plan import RunPlan
from pipeline.planning.provenance import checkpoint_path, checkpoint_record
from pipeline.results.store import RunStore
from pipeline.rundir import (
    CONFIG_YAML,
    EPISODES_DIR,
    LOCK_FILE,
    MARKERS,
    RUN_JSON,
    read_run_json,
    write_run_json,
    write_text_atomic,
)

log = logging.getLogger("idr_eval.runner")


def code_version() -> str:
    here = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        from importlib.metadata import version

        return f"idr-eval-{version('idr-eval')}"


def resume_or_claim(cfg: RunConfig, run_dir: Path, adopt: bool = False) -> str:
    """Return the run id; refuse a RUN_DIR that holds another config's results. ``adopt``:
    take over a run dir whose run.json was lost but whose config.yaml and data are intact."""
    fingerprint = cfg.fingerprint()
    meta = read_run_json(run_dir)
    if meta is not None:
        if meta.get("fingerprint") != fingerprint:
            raise ConfigError(
                f"{run_dir} holds results of a different config (fingerprint {meta.get('fingerprint')} "
                f"vs {fingerprint}); results of two configs are never mixed. Use a new --out, or "
                f"delete {run_dir} to start fresh"
            )
        return str(meta["run_id"])
    if not (run_dir.exists() and any(p.name != LOCK_FILE for p in run_dir.iterdir())):
        return uuid.uuid4().hex[:12]
    stored = RunStore(run_dir, read_only=True)
    if not (run_dir / EPISODES_DIR).is_dir():
        raise ConfigError(f"{run_dir} exists and is not an idr-eval run dir; choose an empty --out")
    if not adopt:
        raise ConfigError(
            f"{run_dir} has no {RUN_JSON} but holds {stored.stored_count()} stored episodes (its "
            f"{RUN_JSON} was lost?); pass --adopt to check its config.yaml against this config "
            "and resume it, or choose another --out"
        )
    return _adopt(cfg, run_dir, stored)


def _adopt(cfg: RunConfig, run_dir: Path, stored: RunStore) -> str:
    """The run id of a run dir without run.json, once its config.yaml is this config."""
    from pipeline.planning.config import load_run_record

    saved = run_dir / CONFIG_YAML
    if not saved.is_file():
        raise ConfigError(
            f"--adopt: {run_dir} has no config.yaml, so its episodes cannot be checked against "
            "this config; choose another --out"
        )
    theirs = load_run_record(saved)
    if theirs.fingerprint() != cfg.fingerprint():
        raise ConfigError(
            f"--adopt: {saved} is a different config (fingerprint {theirs.fingerprint()} vs "
            f"{cfg.fingerprint()}); results of two configs are never mixed"
        )
    ids = set(stored.episodes(columns=["run_id"]).column("run_id").to_pylist())
    if len(ids) > 1:
        raise ConfigError(f"--adopt: {run_dir} holds episodes of several runs: {sorted(ids)}")
    run_id = ids.pop() if ids else uuid.uuid4().hex[:12]
    log.warning("adopting %s (run %s): its %s was missing", run_dir, run_id, RUN_JSON)
    return str(run_id)


def misplaced_keys_note(run_dir: Path) -> str | None:
    """What a run dir's episodes ran with, where its config.yaml put intervention keys under
    ``idr:`` (accepted once and silently overridden by the ``intervention:`` defaults; refused
    now): its stored episodes' own columns say which settings were used."""
    from pipeline.planning.config_yaml import safe_load_yaml
    from pipeline.planning.grid import INTERVENTION_KEYS

    saved = run_dir / CONFIG_YAML
    if not saved.is_file():
        return None
    try:
        data = safe_load_yaml(saved.read_text()) or {}
    except Exception:  # an unreadable config.yaml: nothing to add to the config's own error
        return None
    idr = data.get("idr") if isinstance(data, dict) else None
    misplaced = [k for k in (idr or {}) if k in INTERVENTION_KEYS]
    if not misplaced:
        return None
    stored = RunStore(run_dir, read_only=True)
    table = stored.episodes(columns=misplaced)
    ran = {k: sorted({str(v) for v in table.column(k).to_pylist()}) for k in misplaced}
    said = ", ".join(f"idr.{k}={idr[k]!r}" for k in misplaced)
    used = ", ".join(f"{k} {'/'.join(v) or '(none stored)'}" for k, v in ran.items())
    return (
        f"{run_dir}/{CONFIG_YAML} says {said}, but its {table.num_rows} stored episodes ran with "
        f"{used} (their own columns): those keys were ignored under idr:. Resuming would mix "
        "two settings; rerun into a new --out with the keys under intervention:"
    )


def check_run_dir_intact(run_dir: Path, markers: tuple[str, ...] = MARKERS) -> None:
    """Raise RunDirLostError when the run dir lost ``markers`` (deleted mid-run)."""
    missing = [n for n in markers if not (run_dir / n).exists()]
    if missing:
        raise RunDirLostError(
            f"{run_dir} lost {', '.join(missing)} while this run was writing to it (deleted or "
            "unmounted?): stopping, so that nothing is written into a directory that no longer "
            "holds the run. Episodes stored there may be lost; restore the directory and run "
            "the same command again, or run again with a new --out"
        )


def checkpoint_digest(cfg: RunConfig, run_dir: Path) -> dict[str, object] | None:
    """The checkpoint's digest, reusing run.json's when its files did not change."""
    root = checkpoint_path(cfg)
    if root is None:
        return None
    previous = (read_run_json(run_dir) or {}).get("checkpoint")
    return checkpoint_record(root, previous)


REMOTE_NUMERICS = (
    "the policy server's numerics are its own: identical tables run to run need a server that "
    "runs each request alone or on one fixed shape"
)


def write_meta(plan: RunPlan) -> None:
    plan.run_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(plan.run_dir / CONFIG_YAML, dump_config(plan.cfg))
    meta: dict[str, object] = {
        "run_id": plan.run_id,
        "fingerprint": plan.cfg.fingerprint(),
        "name": plan.cfg.name,
        "code_version": plan.code_version,
    }
    if plan.numerics:
        meta["numerics"] = plan.numerics
    old = read_run_json(plan.run_dir) or {}
    hardware = dict(old.get("hardware") or {})  # every class the run ran on, with its record
    if plan.hardware is not None:
        from workers.hardware import hardware_class

        meta["hardware_class"] = hardware_class(plan.hardware)
        hardware[meta["hardware_class"]] = plan.hardware
    elif old.get("hardware_class"):
        meta["hardware_class"] = old["hardware_class"]
    if hardware:
        meta["hardware"] = hardware
    if plan.numerics == "remote":
        meta["numerics_note"] = REMOTE_NUMERICS
    if plan.checkpoint is not None:
        meta["checkpoint"] = plan.checkpoint
    if plan.env_server is not None:
        meta["env_server"] = plan.env_server
    if plan.fit is not None:
        meta["fit"] = plan.fit.record()
        if plan.fit.protocol:
            meta["protocol"] = dict(plan.fit.protocol)
    kept = old.get("quarantined")  # what earlier drivers recorded (quarantined files) is kept
    if kept:
        meta["quarantined"] = kept
    write_run_json(plan.run_dir, meta)
