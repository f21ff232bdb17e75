"""LIBERO-PRO (``env.suite: libero_pro``) in its env server, from .venv-liberopro: the suites'
tasks and pairing, the instruction the policy receives (the reworded one of ``_lan``, read from
the problem file, LIBERO-PRO issue #27), and one error before any work per bad input.

The server tests are skipped, with the reason, where `make setup-liberopro` has not built
.venv-liberopro (`make test` builds it); the refusals without it always run."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, config_from_dict
from workers.envs.suites.libero.pro import families

ROOT = Path(__file__).resolve().parents[3]
PYTHON = Path(os.environ.get("IDR_LIBEROPRO_PYTHON", ROOT / ".venv-liberopro" / "bin" / "python"))
needs_server = pytest.mark.skipif(
    not PYTHON.exists(), reason=f"no LIBERO-PRO interpreter at {PYTHON}: make setup-liberopro"
)


def _cfg(python: str | None, params: dict | None = None, **over) -> object:
    return config_from_dict(
        {
            "name": "libero_pro",
            "backbone": {"kind": "noop", "params": {"action_dim": 7, "gripper_value": -1.0}},
            "env": {
                "suite": "libero_pro",
                "python": python,
                "params": params or {},
                **over.pop("env", {}),
            },
            "episodes_per_task": 1,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
            **over,
        }
    )


def test_suite_names_split_into_the_original_and_the_family() -> None:
    assert families.split_suite("libero_spatial_swap") == ("libero_spatial", "swap")
    assert families.split_suite("libero_10_with_mug") == ("libero_10", "with_mug")
    assert families.split_suite("libero_goal") == ("libero_goal", "original")
    assert len(families.DEFAULT_SUITES) == 20  # 4 originals x (original + 4 families)
    assert "libero_goal_with_rotated_stick" in families.KNOWN_SUITES
    assert "libero_10_with_rotated_stick" not in families.KNOWN_SUITES  # not in the package


def test_without_its_interpreter_it_is_refused_naming_the_make_target(tmp_path) -> None:
    before = os.environ.get("LIBERO_CONFIG_PATH")
    with pytest.raises(ConfigError, match=r"make setup-liberopro.*env.python=\.venv-liberopro"):
        plan_run(_cfg(None), tmp_path / "a")
    with pytest.raises(
        ConfigError, match=r"env.python=.*no such interpreter.*make setup-liberopro"
    ):
        plan_run(_cfg(str(tmp_path / "nope" / "python")), tmp_path / "b")
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()
    # hf-libero (this interpreter's LIBERO) reads its config from there: left as it was
    assert os.environ.get("LIBERO_CONFIG_PATH") == before


def test_an_unknown_suite_is_refused_with_did_you_mean(tmp_path) -> None:
    with pytest.raises(
        ConfigError, match=r"libero_spatial_swapp.*did you mean libero_spatial_swap"
    ):
        plan_run(_cfg(str(PYTHON), {"suites": ["libero_spatial_swapp"]}), tmp_path / "a")
    assert not (tmp_path / "a").exists()


def _problem_language(suite: str, index: int) -> str:
    """The ``:language`` of the task's problem file, read in the LIBERO-PRO interpreter with
    LIBERO's own parser (independently of the suite's code)."""
    code = (
        "import os, sys, contextlib, io\n"
        "os.environ['LIBERO_CONFIG_PATH'] = sys.prefix + '/nothing-here'\n"
        "from libero.libero import benchmark\n"
        "from libero.libero.envs.bddl_utils import get_problem_info\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        f"    b = benchmark.get_benchmark_dict()[{suite!r}]()\n"
        f"print(get_problem_info(b.get_task_bddl_file_path({index}))['language_instruction'])\n"
    )
    out = subprocess.run([str(PYTHON), "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.strip().splitlines()[-1]


@needs_server
@pytest.mark.slow
def test_tasks_pair_with_their_originals_and_lan_shows_the_reworded_instruction(tmp_path):
    from workers.episode.worker import EpisodeWorker

    tasks = ["libero_spatial/3", "libero_spatial_lan/3", "libero_spatial_task/3"]
    params = {
        "suites": ["libero_spatial", "libero_spatial_lan", "libero_spatial_task"],
        "max_steps": {
            s: 3 for s in ("libero_spatial", "libero_spatial_lan", "libero_spatial_task")
        },
    }
    plan = plan_run(_cfg(str(PYTHON), params, env={"tasks": tasks}), tmp_path / "run")
    assert [s.task_id for s in plan.specs] == tasks
    worker = EpisodeWorker(plan.worker_spec)
    received: list[str] = []
    predict = worker.backbone.predict_chunk

    def recording(obs, *args, **kwargs):
        received.append(obs.instruction[0])
        return predict(obs, *args, **kwargs)

    worker.backbone.predict_chunk = recording
    rows = []
    try:
        assert worker.env.hello["executable"].startswith(str(PYTHON.parent.parent))
        for spec in plan.specs:
            received.append("|")
            rows.append(worker.run_episode(spec).episode)
    finally:
        worker.close()
    assert [r.error for r in rows] == [None] * 3 and [r.steps for r in rows] == [3] * 3
    by_episode = "".join(f"\n{x}" for x in received).split("\n|")[1:]
    seen = [{line for line in chunk.split("\n") if line} for chunk in by_episode]
    original, lan, task = (r.instruction for r in rows)
    # lerobot and openpi show LIBERO's table wording for an original task ...
    assert original == "pick up the black bowl on the cookie box and place it on the plate"
    # ... and the reworded one, from the problem file the env loaded, for its _lan twin
    assert lan == _problem_language("libero_spatial_lan", 3) != original
    assert task == _problem_language("libero_spatial_task", 3) != original
    assert seen == [{original}, {lan}, {task}]  # what the policy received, at every inference
    assert rows[1].init_state_id == "libero_spatial_lan/3/init0"


@needs_server
def test_bad_input_with_the_server_is_refused_before_work(tmp_path) -> None:
    py = str(PYTHON)
    one = {"suites": ["libero_spatial_swap"]}
    with pytest.raises(ConfigError, match=r"episodes_per_task=51.*have 50 episodes"):
        plan_run(_cfg(py, one, episodes_per_task=51), tmp_path / "a")
    with pytest.raises(ConfigError, match=r"libero_spatial_with_red_stick.*red_sticker\.xml"):
        plan_run(_cfg(py, {"suites": ["libero_spatial_with_red_stick"]}), tmp_path / "b")
    with pytest.raises(ConfigError, match=r"libero_spatial_env.*libero_spatial_env/.*\.bddl"):
        plan_run(_cfg(py, {"suites": ["libero_spatial_env"]}), tmp_path / "c")
    with pytest.raises(ConfigError, match=r"env.tasks: \['libero_spatial/0'\] not in suite"):
        plan_run(_cfg(py, one, env={"tasks": ["libero_spatial/0"]}), tmp_path / "d")
    assert not any((tmp_path / d).exists() for d in "abcd")


@needs_server
def test_the_servers_state_arithmetic_is_ours_bit_for_bit(tmp_path) -> None:
    """Both protocols' state (openpi: numpy float64 axis-angle; lerobot: torch float32), computed
    by the LIBERO-PRO interpreter on 2,000 raw observations (random unit quaternions, near-identity
    ones among them), equals this interpreter's to the bit."""
    from workers.envs.suites.libero.protocol import state_vector

    rng = np.random.default_rng(0)
    quats = rng.normal(size=(2000, 4))
    quats[:50] = [0.0, 0.0, 1e-9, 1.0]  # the zero-rotation branch
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    raw = {
        "robot0_eef_pos": rng.normal(size=(2000, 3)),
        "robot0_eef_quat": quats,
        "robot0_gripper_qpos": rng.normal(size=(2000, 2)) * 0.04,
    }
    np.savez(tmp_path / "raw.npz", **raw)
    code = (
        "import sys, numpy as np\n"
        "from workers.envs.suites.libero.protocol import state_vector\n"
        f"raw = np.load({str(tmp_path / 'raw.npz')!r})\n"
        "out = {str(f): np.stack([state_vector({k: raw[k][i] for k in raw.files}, f)\n"
        "       for i in range(len(raw['robot0_eef_quat']))]) for f in (False, True)}\n"
        f"np.savez({str(tmp_path / 'theirs.npz')!r}, **out)\n"
    )
    subprocess.run([str(PYTHON), "-c", code], cwd=ROOT, check=True, capture_output=True)
    theirs = np.load(tmp_path / "theirs.npz")
    for f32 in (False, True):
        ours = np.stack([state_vector({k: v[i] for k, v in raw.items()}, f32) for i in range(2000)])
        assert ours.dtype == theirs[str(f32)].dtype == np.float32
        assert ours.tobytes() == theirs[str(f32)].tobytes(), f"float32_state={f32}"


@needs_server
@pytest.mark.parametrize(
    ("preset", "episodes", "image_size"),
    # the grid's E cell is planned once diagnose has calibrated tau: baseline + diagnose first
    [("libero_pro_smoke.yaml", 5, 256), ("grids/libero_pro.yaml", 40, 96)],
)
def test_the_presets_plan(tmp_path, preset, episodes, image_size) -> None:
    from pipeline.planning.config import load_config

    cfg = load_config(ROOT / "conf" / preset, ["executor.kind=inline", "tracking.enabled=false"])
    plan = plan_run(cfg, tmp_path / "run")
    assert len(plan.specs) == episodes
    # openpi's fixed 256 px; under lerobot's protocol the checkpoint's (the tiny VLA's 96)
    assert plan.fit.protocol["image_size"] == image_size
