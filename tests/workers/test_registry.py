"""Classes by registered name or by entry point ("package.module:Class"), with clear errors."""

from __future__ import annotations

import pytest

from workers.backbones.factory import BACKBONES
from workers.envs.factory import ENVS, check_suite, suite_tasks
from workers.envs.fakes import FakeMarkerEnv
from workers.registry import load_class


def test_registered_names_and_entry_points_load_the_same_class() -> None:
    assert load_class(ENVS, "fake_marker", "env.suite") is FakeMarkerEnv
    assert load_class(ENVS, "workers.envs.fakes:FakeMarkerEnv", "env.suite") is FakeMarkerEnv
    from tests.doubles.envs import FaultyMarkerEnv

    assert load_class(ENVS, "tests.doubles.envs:FaultyMarkerEnv", "env.suite") is FaultyMarkerEnv


@pytest.mark.parametrize(
    ("name", "pattern"),
    [
        ("fake_markr", r"env\.suite='fake_markr' is unknown; did you mean 'fake_marker'\?"),
        ("no_such_pkg.mod:Env", r"cannot import module 'no_such_pkg.mod'"),
        ("workers.envs.fakes:NoSuchEnv", r"module 'workers.envs.fakes' has no 'NoSuchEnv'"),
        ("workers.envs.fakes:IMAGE_SIZE", r"is not a class"),
        ("workers.envs.fakes:", r"an entry point is written 'package.module:Class'"),
        (":FakeMarkerEnv", r"an entry point is written 'package.module:Class'"),
    ],
)
def test_bad_names_are_one_error_naming_the_field(name, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        load_class(ENVS, name, "env.suite")


def test_an_entry_point_env_keeps_its_own_suite_name() -> None:
    """Rows and reports name the env's ``suite``, not the entry point that loaded it."""
    check_suite("tests.doubles.envs:FaultyMarkerEnv", {"fail_once": [1]})
    tasks = suite_tasks("tests.doubles.envs:FaultyMarkerEnv", {})
    assert {t.suite for t in tasks} == {"fake_marker"}
    tasks = suite_tasks("tests.doubles.envs:TwoSuiteMarkerEnv", {})
    assert [t.suite for t in tasks] == ["marker_a", "marker_b"]


def test_the_expert_is_registered_outside_backbones_and_envs() -> None:
    assert BACKBONES["tabletop_expert"].startswith("workers.experts.")


def test_an_entry_point_of_the_flat_layout_loads_the_moved_class_with_a_warning():
    """``module:Class`` strings copied from the flat layout keep working (workers.moved)."""
    from workers.envs.suites.tabletop.env import TabletopEnv

    with pytest.warns(FutureWarning, match="workers.envs.suites.tabletop.env:TabletopEnv"):
        cls = load_class({}, "workers.envs.tabletop:TabletopEnv", "env.suite")
    assert cls is TabletopEnv
    with pytest.warns(FutureWarning, match="WebsocketBackbone"):
        cls = load_class({}, "workers.backbones.remote.client:RemoteBackbone", "backbone.kind")
    assert cls.__name__ == "WebsocketBackbone"
