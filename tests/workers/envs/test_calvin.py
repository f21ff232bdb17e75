"""CALVIN's evaluation protocol without a simulator: the shipped sequences, the scene seed
(pyhash's FNV-1), the initial states, the action conversion, and the refusals of the
pre-flight. The simulator's own tests are in test_calvin_sim.py (they need calvin_env)."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, load_config
from workers.envs.suites.calvin import checkout as calvin_checkout
from workers.envs.suites.calvin import sequences as calvin_sequences
from workers.envs.suites.calvin.env import CalvinEnv, binarize_gripper
from workers.envs.suites.calvin.sequences import (
    condition_seed,
    fnv1_32,
    initial_state,
    load_sequences,
)

ROOT = Path(__file__).resolve().parents[3]
REF = json.loads((Path(__file__).parent / "data" / "calvin_initial_states_ref.json").read_text())
KEY_ORDER = ["led", "lightbulb", "slider", "drawer", "red_block", "blue_block", "pink_block"]


def test_the_shipped_sequences_are_the_official_1000():
    raw = json.loads(calvin_sequences.SEQUENCES_FILE.read_text())
    # the md5 of get_sequences(1000) as the official generator wrote it (json.dumps of the list)
    assert hashlib.md5(json.dumps(raw).encode()).hexdigest() == "ecdfad2eace34cae15d88471f260a2bf"
    seqs = load_sequences()
    assert len(seqs) == 1000
    assert all(list(cond)[:7] == KEY_ORDER for cond, _ in seqs)  # the seed depends on the order
    assert all(len(set(tasks)) == 5 for _, tasks in seqs)
    assert len({json.dumps(cond) for cond, _ in seqs}) == 192  # every valid initial state
    assert len({t for _, tasks in seqs for t in tasks}) == 34
    assert Counter(tasks[0] for _, tasks in seqs).most_common(1) == [("open_drawer", 115)]


def test_fnv1_32_is_pyhashs_variant():
    # FNV-1 from 0 over UTF-16-LE (pyhash), not the FNV offset basis over UTF-8
    assert fnv1_32("") == 0
    # "a" is b"a\x00" in UTF-16-LE: (0 * p) ^ 0x61, then (0x61 * p) ^ 0x00
    assert fnv1_32("a") == (0x61 * 0x01000193) & 0xFFFFFFFF
    text = "dict_values([1, 1, 'left', 'open', 'slider_left', 'table', 'slider_right', 0])"
    assert fnv1_32(text) == 2138410836  # pyhash.fnv1_32()(text), measured


@pytest.mark.parametrize("ref", REF["states"], ids=lambda r: f"seq{r['sequence']}")
def test_initial_states_match_the_official_function_bit_for_bit(ref):
    cond, _ = load_sequences()[ref["sequence"]]
    assert condition_seed(cond) == ref["seed"]
    robot_obs, scene_obs = initial_state(cond)
    assert robot_obs.tolist() == ref["robot_obs"]
    assert scene_obs.tolist() == ref["scene_obs"]


def test_initial_state_leaves_numpys_global_rng_alone():
    np.random.seed(3)
    expected = np.random.random()
    np.random.seed(3)
    initial_state(load_sequences()[0][0])
    assert np.random.random() == expected


def test_gripper_is_binarized_on_a_fresh_float64_copy():
    a = np.array([0.5, -0.5, 0, 0, 0, 0.1, 0.3], dtype=np.float32)
    out = binarize_gripper(a)
    assert out.dtype == np.float64 and out[6] == 1.0 and a[6] == np.float32(0.3)
    assert binarize_gripper(np.r_[np.zeros(6), 0.0])[6] == -1.0  # 0 closes, as the official wrapper
    assert binarize_gripper(np.r_[np.zeros(6), -0.2])[6] == -1.0
    assert np.array_equal(out[:6], a[:6].astype(np.float64))


def test_tasks_and_io_are_known_without_a_simulator():
    (task,) = CalvinEnv.suite_tasks()
    assert (task.task_id, task.max_steps, task.subtasks_total) == ("scene_D", 1800, 5)
    io = CalvinEnv.describe()
    assert io.cameras == ("rgb_static", "rgb_gripper")
    assert (io.hw_of("rgb_static"), io.hw_of("rgb_gripper")) == ((200, 200), (84, 84))
    assert (io.state_dim, io.action_dim) == (15, 7)
    assert io.protocol["subtask_steps"] == 360 and io.protocol["renderer"] == "pybullet-egl"


def _fake_checkout(tmp_path: Path) -> Path:
    """The folders the checks look at (not calvin_env: nothing runs from it)."""
    root = tmp_path / "calvin" / "calvin_env"
    (root / "calvin_env" / "envs").mkdir(parents=True)
    (root / "calvin_env" / "envs" / "play_table_env.py").write_text("")
    for folder, name in (
        ("scene", "calvin_scene_D"),
        ("scene", "calvin_scene_A"),
        ("robot", "panda_longer_finger"),
    ):
        (root / "conf" / folder).mkdir(parents=True, exist_ok=True)
        (root / "conf" / folder / f"{name}.yaml").write_text("")
    for needed in calvin_checkout.CONF_NEEDED:
        (root / "conf" / needed).parent.mkdir(parents=True, exist_ok=True)
        (root / "conf" / needed).write_text("")
    ann = tmp_path / "calvin" / calvin_checkout.ANNOTATIONS_IN_CALVIN
    ann.parent.mkdir(parents=True)
    ann.write_text("open_drawer: [pull the handle to open the drawer]\n")
    return root


def test_an_incomplete_checkout_is_refused_naming_what_it_lacks(tmp_path) -> None:
    """A copy of calvin_env without the config groups the env is composed from (a snapshot
    that dropped conf/env and conf/vr_input) is refused before any work, naming them."""
    root = _fake_checkout(tmp_path)
    (root / "conf" / "env" / "play_table_env.yaml").unlink()
    with pytest.raises(
        ValueError, match=r"incomplete calvin_env checkout.*'env/play_table_env.yaml'"
    ):
        calvin_checkout.find_checkout(str(root))


@pytest.mark.parametrize(
    ("params", "pattern"),
    [
        ({"calvin_env": "/nonexistent"}, r"env.params.calvin_env=/nonexistent: not a calvin_env"),
        (
            {"scene": "calvin_scene_E"},
            r"env.params.scene='calvin_scene_E' is not in .*calvin_scene_A",
        ),
        ({"cameras": ["rgb_tactile"]}, r"env.params.cameras=\['rgb_tactile'\]: choose from"),
        ({"renderer": "opengl"}, r"env.params.renderer='opengl'"),
        (
            {"annotations": "/nonexistent.yaml"},
            r"env.params.annotations=/nonexistent.yaml: no such",
        ),
    ],
)
def test_runtime_check_names_the_field(tmp_path, params, pattern):
    params = {"calvin_env": str(_fake_checkout(tmp_path)), **params}
    with pytest.raises(ValueError, match=pattern):
        CalvinEnv.check_runtime(**params)


def test_no_checkout_is_refused_with_where_to_get_it(monkeypatch):
    monkeypatch.delenv("CALVIN_ENV", raising=False)
    with pytest.raises(ValueError, match=r"env.params.calvin_env is not set .* \$CALVIN_ENV"):
        CalvinEnv.check_runtime()


def test_the_preset_is_refused_before_any_work_without_its_interpreter(tmp_path, monkeypatch):
    monkeypatch.setenv("CALVIN_ENV", str(_fake_checkout(tmp_path)))
    cfg = load_config(
        ROOT / "conf" / "calvin_smoke.yaml",
        ["tracking.enabled=false", f"env.python={tmp_path / 'no-venv' / 'bin' / 'python'}"],
    )
    with pytest.raises(ConfigError, match=r"env.python=.*no such interpreter \(make setup-calvin"):
        plan_run(cfg, tmp_path / "run")
    # in this process (Python 3.12): PyBullet is not here, and the error says where it is
    cfg = load_config(
        ROOT / "conf" / "calvin_smoke.yaml", ["tracking.enabled=false", "env.python=null"]
    )
    with pytest.raises(ConfigError, match=r"needs \['pybullet'.*make setup-calvin"):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


SERVER_SIDE = [
    "workers/envs/server/wire.py",
    "workers/envs/server/serve.py",
    "workers/envs/base.py",
    "workers/envs/suites/calvin/env.py",
    "workers/envs/suites/calvin/checkout.py",
    "workers/envs/suites/calvin/sequences.py",
    "workers/io_spec.py",
    "workers/registry.py",
]


def _python311() -> str | None:
    found = shutil.which("python3.11")
    if found:
        return found
    for p in sorted(Path.home().glob(".pyenv/versions/3.11*/bin/python3.11")):
        return str(p)
    return None


@pytest.mark.skipif(_python311() is None, reason="no Python 3.11 on this machine (pyenv 3.11)")
def test_what_the_env_server_imports_compiles_on_python_3_11():
    """The env server runs these in CALVIN's Python 3.11: no 3.12-only syntax (ruff targets 3.12)."""
    code = "import sys, ast; [ast.parse(open(f).read(), f) for f in sys.argv[1:]]"
    r = subprocess.run(
        [_python311(), "-c", code, *SERVER_SIDE], cwd=ROOT, capture_output=True, text=True
    )
    assert r.returncode == 0, r.stderr
