"""``idr-eval list``: what a config can name, read from the registries (never a fixed list)."""

from __future__ import annotations

import importlib.util

import pytest

from pipeline.cli import main
from workers.envs.factory import ENVS
from workers.envs.wrappers.perturbation_grammar import KINDS


def test_list_names_every_suite_env_type_kind_and_backbone(capsys) -> None:
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    for section in ("# suites", "# envs", "# perturbations", "# backbones"):
        assert section in out
    lines = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert set(ENVS) <= set(lines) and set(KINDS) <= set(lines)
    pusht = importlib.util.find_spec("gym_pusht") is not None
    assert lines["pusht"].split()[2] == ("yes" if pusht else "no")
    assert "parity with lerobot-eval tested" in lines["pusht"]
    assert "refused: use env.suite=libero" in lines["libero"]
    assert lines["camera_shift"].endswith("tabletop, libero, libero_pro")
    assert lines["image_noise"].endswith("every suite")


def test_list_tasks_of_a_suite_with_its_params(capsys) -> None:
    assert main(["list", "tasks", "fake_marker"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].split() == ["task", "name", "max", "steps"]
    assert [line.split()[0] for line in out[1:]] == ["reach", "reach_chain"]
    if importlib.util.find_spec("gym_pusht") is not None:
        assert main(["list", "tasks", "lerobot", "type=pusht"]) == 0
        rows = [line.split() for line in capsys.readouterr().out.splitlines()]
        assert ["pusht", "pusht:pusht", "300"] in rows


@pytest.mark.parametrize(
    ("argv", "pattern"),
    [
        (["list", "tasks"], "name a suite"),
        (["list", "tasks", "tabletopp"], "tabletop"),
        (["list", "tasks", "fake_marker", "image_size"], "key=value"),
    ],
)
def test_list_refuses_bad_input_with_one_error(argv, pattern, capsys) -> None:
    assert main(argv) == 2
    assert pattern in capsys.readouterr().err
