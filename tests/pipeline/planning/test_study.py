"""Study files: every run's config checked before any work, errors naming the entry."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.planning.config import ConfigError
from pipeline.planning.study import load_study

CONF = Path(__file__).resolve().parents[3] / "conf"
SMOKE = str(CONF / "smoke.yaml")


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "study.yaml"
    p.write_text(text)
    return p


def test_runs_get_shared_then_own_then_cli_overrides(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        f"""
name: s
set: [episodes_per_task=2, seed=3]
runs:
  - {{arch: a, env: fake, config: {SMOKE}, set: [episodes_per_task=4]}}
  - {{arch: b, env: fake, config: {SMOKE}}}
""",
    )
    study = load_study(p, ["seed=5"])
    assert [r.label for r in study.runs] == ["a@fake", "b@fake"]
    assert [r.config.episodes_per_task for r in study.runs] == [4, 2]  # own beats shared
    assert {r.config.seed for r in study.runs} == {5}  # the command line beats both


def test_a_bad_key_in_a_later_run_is_refused_naming_it(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        f"""
runs:
  - {{arch: a, env: fake, config: {SMOKE}}}
  - {{arch: b, env: fake, config: {SMOKE}, set: [episodes_per_tsk=4]}}
""",
    )
    with pytest.raises(ConfigError, match=r"(?s)runs\[1\] \(b@fake\).*episodes_per_tsk"):
        load_study(p)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("runs: []", "non-empty list"),
        ("name: x", "runs:"),
        (f"runs: [{{arch: a, config: {SMOKE}}}]", r"missing \['env'\]"),
        (f"runs: [{{arch: a, env: e, config: {SMOKE}, sed: 1}}]", r"unknown keys \['sed'\]"),
        (f"runs: [{{arch: a, env: e, config: {SMOKE}, seed: -1}}]", r"seed: .*integer >= 0"),
        (
            f"runs: [{{arch: a, env: e, config: {SMOKE}, seed: 0}}, "
            f"{{arch: a, env: e, config: {SMOKE}}}]",
            r"runs of a@e: 1 without a seed beside seeds \[0\]; give every run",
        ),
        (
            f"runs: [{{arch: a, env: e, config: {SMOKE}, seed: 2}}, "
            f"{{arch: a, env: e, config: {SMOKE}, seed: 2}}]",
            r"a@e:seed2.*appear twice",
        ),
        (f"runs: [{{arch: a, env: e, config: {SMOKE}, set: seed}}]", "key=value"),
        (
            f"runs: [{{arch: a, env: e, config: {SMOKE}}}, {{arch: a, env: e, config: {SMOKE}}}]",
            "appear twice",
        ),
        ("runs: [{arch: a, env: e, config: conf/nope.yaml}]", "nope.yaml"),
    ],
)
def test_malformed_studies_are_refused(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_study(_write(tmp_path, text))


def test_the_shipped_observations_study_loads() -> None:
    study = load_study(CONF / "paper" / "observations.yaml")
    assert {r.arch for r in study.runs} >= {"tiny_vla", "act", "xvla", "smolvla"}
    assert all(r.config.episodes_per_task == 10 for r in study.runs)
    for r in study.runs:
        # lerobot's architectures on the tabletop: the members trained without the orientation
        # dims, evaluated on the same state dims
        pos = r.env == "tabletop" and r.arch != "tiny_vla"
        sub = "tabletop_pos/" if pos else "" if r.env == "tabletop" else f"{r.env}/"
        assert r.config.backbone.params["path"] == f"checkpoints/zoo/{sub}{r.arch}"
        assert r.config.env.params.get("state_dims") == ([0, 1, 2, 6, 7] if pos else None)
    assert {r.env for r in study.runs} == {"tabletop", "metaworld"}


def test_only_keeps_the_named_runs_and_refuses_a_label_not_in_the_study(tmp_path: Path) -> None:
    p = _write(
        tmp_path,
        f"""
runs:
  - {{arch: a, env: fake, config: {SMOKE}}}
  - {{arch: b, env: fake, config: conf/nope.yaml}}
  - {{arch: c, env: fake, config: {SMOKE}}}
""",
    )
    # the runs left out are not loaded: b's config file does not exist
    assert [r.label for r in load_study(p, only=["c@fake", "a@fake"]).runs] == ["a@fake", "c@fake"]
    with pytest.raises(ConfigError, match=r"\['d@fake'\] not in .*a@fake, b@fake, c@fake"):
        load_study(p, only=["a@fake", "d@fake"])
    with pytest.raises(ConfigError, match="no run"):
        load_study(p, only=[])


def test_the_confirmatory_study_declares_seeded_members_and_says_how_each_is_built() -> None:
    """Declared before its data: three training seeds per member, 30 episodes per task, a
    held-out calibration, E against diagnose and against its random placebo per member; every
    checkpoint it names is shipped or listed with the command that builds it."""
    import json

    study = load_study(CONF / "paper" / "confirmatory.yaml")
    seeds: dict[str, set] = {}
    for r in study.runs:
        seeds.setdefault(r.member, set()).add(r.seed)
        assert r.config.episodes_per_task == 30 and r.config.calibration is not None
        assert [c.cell_id for c in r.config.cells()] == ["diagnose", "E", "random"]
        path = Path(r.config.backbone.params["path"])
        rebuild = json.loads((path.parent / "REBUILD.json").read_text())
        assert (path / "config.json").is_file() or path.name in rebuild, path
    assert seeds == {
        m: {0, 1, 2} for m in ("tiny_vla@metaworld", "act@metaworld", "smolvla@metaworld")
    }
    declared = {(e.member, e.cell, e.reference) for e in study.endpoints}
    assert declared == {(m, "E", ref) for m in seeds for ref in ("diagnose", "random")}
