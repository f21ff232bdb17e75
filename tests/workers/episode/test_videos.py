"""Episode videos (``videos.episodes``): the first N episodes of each task and cell as MP4 in the
run dir, frame for frame the episode's camera, and as artifacts of the cell's MLflow run; off by
default; a camera the env does not render is an error."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"


def _run(tmp_path: Path, *overrides: str):
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "episodes_per_task=2",
            f"tracking.uri=sqlite:///{tmp_path / 'mlflow.db'}",
            *overrides,
        ],
    )
    return execute(plan_run(cfg, tmp_path / "run"))


def test_the_first_episodes_of_each_task_and_cell_are_videos_in_the_run_and_mlflow(tmp_path):
    import mlflow

    summary = _run(tmp_path, "videos.episodes=1", "videos.fps=10")
    assert summary.errors == 0
    videos = sorted((tmp_path / "run" / "videos").rglob("*.mp4"))
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    first = eps[eps.episode_index == 0]
    assert len(videos) == len(first) == 4  # 2 cells x 2 tasks, episode 0 only
    for _, row in first.iterrows():
        path = tmp_path / "run" / "videos" / f"cell={row.cell_id}" / row.task_id / "episode_0.mp4"
        frames = iio.imread(path)
        assert frames.shape[0] == row.steps + 1  # the reset and every step
        assert frames.shape[1:] == (32, 32, 3)  # the fake env's camera
    client = mlflow.MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId")]
    assert len(children) == 2
    for child in children:
        names = {a.path for a in client.list_artifacts(child.info.run_id, "videos")}
        assert names == {"videos/reach", "videos/reach_chain"}


def test_no_videos_by_default_and_an_unknown_camera_is_refused_before_work(tmp_path) -> None:
    _run(tmp_path / "a", "tracking.enabled=false")
    assert not (tmp_path / "a" / "run" / "videos").exists()
    with pytest.raises(ConfigError, match=r"videos.camera='top': suite 'fake_marker' renders"):
        _run(tmp_path / "b", "tracking.enabled=false", "videos.episodes=1", "videos.camera=top")
    assert not (tmp_path / "b" / "run").exists()
