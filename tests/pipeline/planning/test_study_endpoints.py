"""A study's declared endpoints and calibration: refused before any episode where they name
what the study lacks, pinned by hash before the first episode, and frozen once it holds one."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.planning.config import ConfigError
from pipeline.planning.study import ENDPOINTS_FILE, endpoints_hash, load_study

CONF = Path(__file__).resolve().parents[3] / "conf"
SMOKE = CONF / "smoke.yaml"
COMMON = "executor.kind=inline, executor.workers=1, tracking.enabled=false"


def _study(tmp_path: Path, endpoints: str, extra: str = "") -> Path:
    p = tmp_path / "study.yaml"
    p.write_text(
        f"""
name: s
set: [episodes_per_task=1, "grid=[{{mode: [diagnose, E]}}]", {COMMON}{extra}]
runs:
  - {{arch: a, env: fake, config: {SMOKE}}}
  - {{arch: b, env: fake, config: {SMOKE}}}
{endpoints}
"""
    )
    return p


TWO = """endpoints:
  primary:
    - {member: a@fake, compare: [E, diagnose]}
    - {member: b@fake, compare: [E, diagnose], suite: fake_marker}
"""


def test_endpoints_are_read_in_their_declared_order(tmp_path: Path) -> None:
    study = load_study(_study(tmp_path, TWO))
    assert [e.label for e in study.endpoints] == [
        "a@fake: E vs diagnose",
        "b@fake: E vs diagnose [fake_marker]",
    ]
    assert study.endpoints_hash() == endpoints_hash(study.endpoints)
    assert study.endpoints_hash() != endpoints_hash(study.endpoints[::-1])


@pytest.mark.parametrize(
    ("endpoints", "match"),
    [
        (
            "endpoints: {primary: [{member: a@fak, compare: [E, diagnose]}]}",
            r"endpoints\.primary\[0\]\.member: 'a@fak' is not a member or run of this study; "
            r"did you mean 'a@fake'",
        ),
        (
            "endpoints: {primary: [{member: a@fake, compare: [F, diagnose]}]}",
            r"endpoints\.primary\[0\]\.compare: a@fake has no cell 'F'; its cells are",
        ),
        (
            "endpoints: {primary: [{member: a@fake, compare: [E]}]}",
            r"endpoints\.primary\[0\]\.compare: two different cells",
        ),
        (
            "endpoints: {primary: [{member: a@fake, compare: [E, diagnose], alpha: 1}]}",
            r"endpoints\.primary\[0\]: unknown keys \['alpha'\]",
        ),
        ("endpoints: [a@fake]", r"endpoints: write endpoints: \{primary:"),
    ],
)
def test_an_endpoint_the_study_lacks_is_refused(tmp_path: Path, endpoints: str, match) -> None:
    with pytest.raises(ConfigError, match=match):
        load_study(_study(tmp_path, endpoints))


def test_an_endpoint_suite_the_member_lacks_is_refused_before_any_episode(
    tmp_path: Path, capsys
) -> None:
    p = _study(tmp_path, "endpoints: {primary: [{member: a@fake, compare: [E, diagnose], "
               "suite: tabletop}]}")  # fmt: skip
    out = tmp_path / "out"
    assert cli.main(["study", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "endpoints.primary[0].suite: a@fake has no suite 'tabletop'" in err
    assert "['fake_marker']" in err
    assert not list(out.glob("**/*.parquet")) and not (out / ENDPOINTS_FILE).exists()


def test_a_calibrated_run_without_a_calibration_block_is_refused(tmp_path: Path, capsys) -> None:
    p = _study(tmp_path, "", extra=", idr.tau=calibrated")
    out = tmp_path / "out"
    assert cli.main(["study", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "a@fake: calibration: a study fits tau on held-out episodes" in err
    assert "calibration={episodes_per_task: 10}" in err
    assert not list(out.glob("**/*.parquet"))


def test_changing_the_endpoints_of_a_study_with_episodes_is_refused(tmp_path: Path, capsys) -> None:
    out = tmp_path / "out"
    one = "endpoints: {primary: [{member: a@fake, compare: [E, diagnose]}]}"
    p = _study(tmp_path, one)
    assert cli.main(["study", str(p), "--out", str(out)]) == 0
    pinned = json.loads((out / ENDPOINTS_FILE).read_text())
    assert pinned["hash"] == load_study(p).endpoints_hash()
    assert pinned["primary"] == [
        {"member": "a@fake", "cell": "E", "reference": "diagnose", "suite": None}
    ]
    # the same endpoints: resumed
    assert cli.main(["study", str(p), "--out", str(out)]) == 0
    # another endpoint added after the data: refused, naming the file and a new study
    p = _study(tmp_path, TWO)
    capsys.readouterr()
    assert cli.main(["study", str(p), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{p}: endpoints: the declared primary endpoints differ" in err
    assert str(out / ENDPOINTS_FILE) in err and f"--out {out}-v2" in err
    assert json.loads((out / ENDPOINTS_FILE).read_text()) == pinned
    # a new study dir takes them
    assert cli.main(["study", str(p), "--out", str(tmp_path / "out-v2")]) == 0


def test_endpoints_may_change_while_the_study_holds_no_episode(tmp_path: Path) -> None:
    from pipeline.planning.study import pin_endpoints

    out = tmp_path / "out"
    first = load_study(_study(tmp_path, "endpoints: {primary: [{member: a@fake, "
                                        "compare: [E, diagnose]}]}"))  # fmt: skip
    pin_endpoints(first, out)
    second = load_study(_study(tmp_path, TWO))
    pin_endpoints(second, out)
    assert json.loads((out / ENDPOINTS_FILE).read_text())["hash"] == second.endpoints_hash()
