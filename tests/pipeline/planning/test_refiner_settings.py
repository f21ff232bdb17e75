"""``idr:`` is a typed model: RefinerConfig's fields one for one, what a config gives kept apart
from the defaults, bad values refused at parse time, and run.json unchanged by the typing."""

from __future__ import annotations

import math

import pytest
from idr_core.refiner import RefinerConfig

from pipeline.errors import ConfigError
from pipeline.planning.config import config_from_dict
from pipeline.planning.refiner_settings import RefinerSettings, refiner_fields

BASE = {"backbone": {"kind": "fake_marker"}, "env": {"suite": "fake_marker"}}


def test_the_model_mirrors_the_refiners_fields() -> None:
    assert sorted(RefinerSettings.model_fields) == sorted(refiner_fields())


def test_settings_are_typed_and_only_the_given_ones_reach_the_cells() -> None:
    grid = [{"mode": ["diagnose", "E"]}]
    cfg = config_from_dict({**BASE, "grid": grid, "idr": {"alpha": 0.2, "tau": "calibrated*2"}})
    assert isinstance(cfg.idr, RefinerSettings)
    assert cfg.idr.given() == {"alpha": 0.2, "tau": "calibrated*2"}
    e = next(c for c in cfg.cells() if c.idr.mode == "E")
    assert e.idr.alpha == 0.2 and e.idr.beta == RefinerConfig().beta
    assert e.calibrated_tau is not None and e.calibrated_tau.text == "calibrated*2"
    # run.json and the fingerprint hold what the config gave, as before the typing
    assert cfg.model_dump()["idr"] == {"alpha": 0.2, "tau": "calibrated*2"}


def test_an_always_open_gate_is_a_number() -> None:
    cfg = config_from_dict({**BASE, "idr": {"tau": math.inf}})
    assert cfg.idr.tau == math.inf


@pytest.mark.parametrize(
    ("idr", "pattern"),
    [
        ({"alpah": 0.1}, r"idr.alpah: unknown key; did you mean 'alpha'"),
        ({"strategy": "mean"}, r"'strategy' is an intervention setting.*intervention:"),
        ({"alpha": -0.1}, r"idr: .*alpha=-0.1 must be a number >= 0"),
        ({"mode": "Q"}, r"idr.mode: Input should be"),
        ({"tau": "calibratd"}, r"idr.tau: .*calibrat"),
        ({"samples": 1}, r"samples=1 must be an integer >= 2"),
    ],
)
def test_a_bad_setting_is_refused_naming_it(idr, pattern) -> None:
    with pytest.raises(ConfigError, match=pattern):
        config_from_dict({**BASE, "idr": idr})
