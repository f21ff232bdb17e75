"""The zoo's path end to end at toy size: recorded parts merged by lerobot's own tool, a member
trained by ``lerobot-train`` through the launcher, stopped and resumed, exported, and loaded by
lerobot's factory with the plugin registered and nothing patched; a dataset that does not fit
the member is refused before training."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from training import zoo_benchmarks, zoo_members, zoo_train

# loads a checkpoint folder through lerobot's factory from another working directory and runs
# one chunk through its saved processors: what lerobot-eval does with it
LOAD_AND_ACT = """
import sys, torch
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
path = sys.argv[1]
cfg = PreTrainedConfig.from_pretrained(path)
policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg).eval()
pre, post = make_pre_post_processors(cfg, pretrained_path=path)
obs = {f"observation.images.{c}": torch.rand(1, 3, 96, 96) for c in ("agentview", "wrist")}
obs["observation.state"] = torch.zeros(1, 8)
obs["task"] = ["pick up the red cube"]
with torch.no_grad():
    chunk = post(policy.predict_action_chunk(pre(obs)))
assert chunk.shape[0] == 1 and chunk.shape[-1] == 7 and torch.isfinite(chunk).all(), chunk.shape
print("params", sum(p.numel() for p in policy.parameters()))
"""


def _zoo(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "training.zoo", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=zoo_benchmarks.ROOT,
    )


@pytest.fixture(scope="module")
def toy_dataset(tmp_path_factory) -> Path:
    """Two recorded parts (one episode each) merged by lerobot's merge_datasets."""
    from training.tabletop_demos import record
    from training.zoo_data import merge

    tmp = tmp_path_factory.mktemp("zoo")
    record(tmp / "p1", ["pick_color"], episodes=1, first_episode=100_000)
    record(tmp / "p2", ["stack_color"], episodes=1, first_episode=100_000)
    summary = merge([tmp / "p1", tmp / "p2"], tmp / "ds")
    assert summary["episodes"] == 2 and summary["parts"] == {"p1": 1, "p2": 1}
    assert len(summary["tasks"]) == 2
    return tmp / "ds"


@pytest.mark.sim
@pytest.mark.slow
def test_parts_merge_train_resume_export_and_load_through_lerobots_factory(
    tmp_path, toy_dataset
) -> None:
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    common = ["--dataset", str(toy_dataset), "--runs", str(tmp_path / "runs")]
    first = _zoo("train", "tiny_vla", "--steps", "2", *common)
    assert first.returncode == 0, first.stderr[-3000:]
    # resumes from step 2 and is stopped by its time limit before its 100,000 steps (a session
    # with an allotment); what it saved until then is kept
    second = _zoo(
        "train", "tiny_vla", "--steps", "100000", "--save-freq", "1", "--time-limit-s", "40",
        *common,
    )  # fmt: skip
    assert second.returncode != 0 and "--time-limit-s 40 reached" in second.stdout
    assert "--resume=true" in second.stdout
    dest = tmp_path / "ckpt"
    out = _zoo("export", "tiny_vla", "--dest", str(dest), *common)
    assert out.returncode == 0, out.stderr[-3000:]
    meta = json.loads((dest / "train_meta.json").read_text())
    assert 2 < meta["steps"] < 100_000 and meta["sessions"] == 2 and meta["seed"] == 0
    assert meta["devices"] == ["cpu"]
    assert meta["params"] > 200_000
    assert not (dest / "train_config.json").exists()  # it held this machine's paths

    from lerobot.configs.policies import PreTrainedConfig

    import lerobot_policy_idr  # noqa: F401  (registers tiny_vla, as register_third_party_plugins does)

    cfg = PreTrainedConfig.from_pretrained(dest)
    policy = get_policy_class(cfg.type).from_pretrained(dest, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(dest))
    assert (
        cfg.type == "tiny_vla" and "pick" in cfg.vocab and list(cfg.ignored_state_dims) == [3, 4, 5]
    )
    assert [type(s).__name__ for s in pre.steps][-1] == "NormalizerProcessorStep"
    assert type(post.steps[0]).__name__ == "UnnormalizerProcessorStep"
    assert sum(p.numel() for p in policy.parameters()) == meta["params"]

    # a second stage from the exported weights (a new session whose run folder is gone):
    # lerobot-train's --policy.path, exported over its start with the stages summed
    wrong = _zoo("train", "act", "--init-from", str(dest), *common)
    assert wrong.returncode != 0 and "is a 'tiny_vla' checkpoint" in wrong.stderr
    from safetensors.torch import load_file

    start = load_file(dest / "model.safetensors")
    cont = _zoo("train", "tiny_vla", "--steps", "2", "--init-from", str(dest), *common)
    assert cont.returncode == 0, cont.stderr[-3000:]
    assert f"--policy.path={dest}" in cont.stdout and "--policy.type" not in cont.stdout
    out = _zoo("export", "tiny_vla", "--init-from", str(dest), "--dest", str(dest), *common)
    assert out.returncode == 0, out.stderr[-3000:]
    after = load_file(dest / "model.safetensors")
    # two steps from the exported weights move them a little; a fresh init would be far away
    moved = max(
        ((after[k] - start[k]).norm() / start[k].norm()).item()
        for k in start
        if start[k].is_floating_point() and start[k].norm() > 0
    )
    assert moved < 0.5, moved
    # no path of this machine in the config (lerobot-train recorded the start folder there)
    assert json.loads((dest / "config.json").read_text())["pretrained_path"] is None
    meta2 = json.loads((dest / "train_meta.json").read_text())
    assert meta2["steps"] == meta["steps"] + 2 and meta2["sessions"] == meta["sessions"] + 1
    assert [st["steps"] for st in meta2["stages"]] == [meta["steps"], 2]
    assert meta2["train_seconds"] > meta["train_seconds"]


def test_a_continued_stage_decays_its_schedule_over_its_own_steps() -> None:
    flags = zoo_members.stage_flags(zoo_members.MEMBERS["smolvla"].flags, 5000)
    assert "--policy.scheduler_decay_steps=5000" in flags
    assert not any(f.endswith("=6000") for f in flags)
    xvla = zoo_members.stage_flags(zoo_members.MEMBERS["xvla"].flags, 700)
    assert "--scheduler.num_decay_steps=700" in xvla
    assert len(xvla) == len(zoo_members.MEMBERS["xvla"].flags)


@pytest.mark.slow
def test_a_dataset_that_does_not_fit_the_member_is_refused_before_training(tmp_path) -> None:
    info = {
        "features": {
            "observation.images.agentview": {"shape": [64, 64, 3]},
            "observation.state": {"shape": [8]},
            "action": {"shape": [7]},
        }
    }
    (tmp_path / "ds" / "meta").mkdir(parents=True)
    (tmp_path / "ds" / "meta" / "info.json").write_text(json.dumps(info))
    out = _zoo("train", "act", "--dataset", str(tmp_path / "ds"), "--runs", str(tmp_path / "r"))
    assert out.returncode != 0
    assert "does not fit zoo member 'act'" in out.stderr
    assert "observation.images.agentview: wants [96, 96, 3], dataset has [64, 64, 3]" in out.stderr
    assert "observation.images.wrist: wants [96, 96, 3], dataset has None" in out.stderr
    assert not (tmp_path / "r").exists()  # nothing started


@pytest.mark.slow
def test_an_unknown_member_or_a_missing_dataset_is_named_with_the_fix(tmp_path) -> None:
    out = _zoo("train", "actt", "--dataset", str(tmp_path))
    assert out.returncode != 0 and "unknown zoo member 'actt' (did you mean 'act'?)" in out.stderr
    out = _zoo("train", "act", "--dataset", str(tmp_path / "none"))
    assert "scripts/record_zoo_data.sh" in out.stderr


@pytest.mark.sim
@pytest.mark.slow
@pytest.mark.parametrize("member", ["xvla", "smolvla"])
def test_vlm_members_train_and_load_from_another_folder_by_their_hub_ids(
    tmp_path, toy_dataset, member
) -> None:
    """X-VLA and SmolVLA name their tokenizer / VLM by hub id; the files come from the repo via
    the local HF cache, so the exported checkpoint loads from any working directory."""
    common = ["--dataset", str(toy_dataset), "--runs", str(tmp_path / "runs")]
    out = _zoo("train", member, "--steps", "2", *common)
    assert out.returncode == 0, out.stderr[-3000:]
    dest = tmp_path / "ckpt"
    out = _zoo("export", member, "--dest", str(dest), *common)
    assert out.returncode == 0, out.stderr[-3000:]
    saved = (dest / "config.json").read_text() + (dest / "policy_preprocessor.json").read_text()
    assert (
        "idr-eval/zoo-" in saved and str(zoo_benchmarks.ROOT) not in saved
    )  # no machine path saved
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    run = subprocess.run(
        [sys.executable, "-c", LOAD_AND_ACT, str(dest)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=elsewhere,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    meta = json.loads((dest / "train_meta.json").read_text())
    loaded = int(run.stdout.split("params ")[1].split()[0])
    # train_meta counts the saved tensors (parameters and buffers), the load its parameters
    assert 0.99 * meta["params"] <= loaded <= meta["params"]


def test_every_member_says_how_it_is_rebuilt_and_a_missing_one_is_refused_naming_that() -> None:
    from workers.backbones.lerobot.checkpoint import REBUILD_FILE, check_checkpoint

    commands = json.loads((zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / REBUILD_FILE).read_text())
    assert set(commands) == set(zoo_members.MEMBERS)
    for name, command in commands.items():
        assert f"python -m training.zoo train {name}" in command
        assert "scripts/record_zoo_data.sh" in command
    absent = zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / "no_such_member"
    with pytest.raises(ValueError, match=r"does not exist"):
        check_checkpoint(str(absent))  # no entry: the plain refusal
    missing = [
        n
        for n in zoo_members.MEMBERS
        if not (zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / n).is_dir()
    ]
    for name in missing:  # in a fresh clone: the members not shipped in git
        with pytest.raises(ValueError, match=rf"rebuild it with: .*training.zoo train {name}"):
            check_checkpoint(str(zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / name))


def test_the_zoo_preset_validates() -> None:
    from pipeline.planning.config import load_config

    cfg = load_config(zoo_benchmarks.ROOT / "conf" / "zoo" / "tabletop.yaml")
    assert "pick_color@image_blackout:1" in cfg.env.tasks
    assert [c.idr.mode for c in cfg.cells()] == ["diagnose", "E"]


@pytest.mark.parametrize(
    ("preset", "refusal"),
    [
        # PushT: one 96 px camera `image`, a 2-d state, 2-d actions
        ("pusht_smoke.yaml", r"reads observation\.images\.agentview, which matches no env camera"),
        # MetaWorld: one 480 px camera, a 4-d state, 4-d actions
        ("metaworld_smoke.yaml", r"reads observation\.images\.agentview, which matches no env"),
    ],
)
def test_a_zoo_checkpoint_on_a_suite_it_was_not_trained_on_is_refused_before_work(
    preset, refusal, tmp_path
) -> None:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError, load_config

    ckpt = zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / "tiny_vla"
    cfg = load_config(
        zoo_benchmarks.ROOT / "conf" / preset,
        [
            "backbone.kind=lerobot",
            f"backbone.params={{path: {ckpt}, device: cpu}}",
            "executor.kind=inline",
            "tracking.enabled=false",
        ],
    )
    with pytest.raises(ConfigError, match=refusal):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


@pytest.mark.slow
def test_a_tabletop_dataset_is_refused_for_the_metaworld_benchmark(tmp_path) -> None:
    info = {"features": {k: {"shape": v} for k, v in zoo_benchmarks.TABLETOP_FEATURES.items()}}
    (tmp_path / "ds" / "meta").mkdir(parents=True)
    (tmp_path / "ds" / "meta" / "info.json").write_text(json.dumps(info))
    out = _zoo(
        "train", "tiny_vla", "--benchmark", "metaworld", "--dataset", str(tmp_path / "ds"),
        "--runs", str(tmp_path / "r"),
    )  # fmt: skip
    assert out.returncode != 0 and "on metaworld" in out.stderr
    assert "observation.image: wants [96, 96, 3], dataset has None" in out.stderr
    assert "training.metaworld_demos" in out.stderr and not (tmp_path / "r").exists()
    rebuild = json.loads(
        (zoo_benchmarks.ROOT / "checkpoints/zoo/metaworld/REBUILD.json").read_text()
    )
    # every member, and a second seed under <member>_seed<N> rebuilt with that seed
    assert set(zoo_members.MEMBERS) <= set(rebuild)
    for folder in set(rebuild) - set(zoo_members.MEMBERS):
        member, _, seed = folder.rpartition("_seed")
        assert member in zoo_members.MEMBERS and f"--seed {seed}" in rebuild[folder], folder
        assert f"--dest checkpoints/zoo/metaworld/{folder}" in rebuild[folder]
    assert all("--benchmark metaworld" in c for c in rebuild.values())


@pytest.mark.sim
@pytest.mark.slow
def test_the_state_cut_keeps_every_frame_and_cuts_the_stats_to_match(toy_dataset, tmp_path):
    """training/zoo_state.py: the tabletop_pos dataset lerobot's architectures train on (no
    orientation dims) is the same frames with a 5-d state, stats included."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.zoo_state import derive

    keep = [0, 1, 2, 6, 7]
    out = derive(toy_dataset, tmp_path / "pos", keep)
    src = LeRobotDataset("local/src", root=toy_dataset)
    cut = LeRobotDataset("local/cut", root=out)
    assert len(cut) == len(src) and cut.num_episodes == src.num_episodes
    for i in (0, len(src) // 2, len(src) - 1):
        a, b = src[i], cut[i]
        assert b["observation.state"].shape == (5,)
        assert torch.equal(b["observation.state"], a["observation.state"][keep])
        assert torch.equal(b["action"], a["action"]) and b["task"] == a["task"]
        assert torch.equal(b["observation.images.wrist"], a["observation.images.wrist"])
    for key in ("mean", "std", "min", "max"):
        np.testing.assert_array_equal(
            cut.meta.stats["observation.state"][key], src.meta.stats["observation.state"][key][keep]
        )
    import pyarrow.parquet as pq

    for f in (out / "meta" / "episodes").rglob("*.parquet"):  # the per-episode stats
        for mean in pq.read_table(f, columns=["stats/observation.state/mean"]).column(0):
            assert len(mean.as_py()) == 5
    zoo_train.check_features("act", "tabletop_pos", out)  # fits the benchmark made for it
    with pytest.raises(SystemExit, match=r"observation.state: wants \[8\], dataset has \[5\]"):
        zoo_train.check_features("act", "tabletop", out)
    with pytest.raises(SystemExit, match=r"--keep \[3, 9\]"):
        derive(toy_dataset, tmp_path / "bad", [3, 9])


@pytest.mark.sim
@pytest.mark.slow
def test_the_open_loop_error_of_a_learned_policy_beats_the_mean_action(toy_dataset) -> None:
    from training.zoo_openloop import open_loop_error

    out = open_loop_error(zoo_benchmarks.ROOT / "checkpoints/zoo/tiny_vla", toy_dataset, frames=20)
    assert out["frames"] == 20 and out["dims"] == [0, 1, 2, 6]  # dims 3-5 never vary
    assert len(out["mae_in_std"]) == len(out["mean_action_mae_in_std"]) == 4
    assert out["ratio_to_mean_action"] < 0.6  # the shipped zoo tiny VLA learned the actions


@pytest.mark.sim
@pytest.mark.slow
def test_the_shipped_smolvla_solves_metaworld_from_another_folder_and_fails_without_images(
    tmp_path,
) -> None:
    """The shipped SmolVLA (its VLM named by hub id, resolved from the local cache) run by the
    real CLI from another working directory, offline by idr-eval's own default: it presses the
    button, and with black images at every step it does not."""
    from pipeline.results.store import RunStore

    ckpt = zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED / "metaworld" / "smolvla"
    env = {k: v for k, v in os.environ.items() if not k.endswith("_OFFLINE")}
    out = tmp_path / "run"
    r = subprocess.run(
        [
            sys.executable, "-m", "pipeline.cli", "run",
            str(zoo_benchmarks.ROOT / "conf" / "zoo" / "metaworld.yaml"), "--out", str(out),
            f"backbone.params.path={ckpt}", "executor.kind=inline", "executor.workers=1",
            "tracking.enabled=false", "episodes_per_task=3", "grid=[{mode: [diagnose]}]",
            "env.tasks=[button-press-v3, button-press-v3@image_blackout:1]",
        ],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    episodes = RunStore(out, read_only=True).episodes().to_pandas()
    wins = episodes.groupby("task_id")["success"].sum()
    assert len(episodes) == 6 and wins["button-press-v3"] >= 2, wins
    assert wins["button-press-v3@image_blackout:1"] == 0, wins
    assert "huggingface.co" not in (out / "logs" / "driver.log").read_text()


def test_no_shipped_checkpoint_names_a_folder_of_the_machine_that_trained_it() -> None:
    """lerobot-train writes the folder it loaded from into config.json (pretrained_path); a
    shipped checkpoint must not carry it, since that path exists only where it was trained."""
    configs = sorted((zoo_benchmarks.ROOT / zoo_benchmarks.SHIPPED).rglob("config.json"))
    shipped = [c for c in configs if (c.parent / "model.safetensors").is_file()]
    assert len(shipped) >= 7
    named = [str(c) for c in shipped if json.loads(c.read_text()).get("pretrained_path")]
    assert not named, named
