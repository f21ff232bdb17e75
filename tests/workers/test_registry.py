"""Classes by registered name or by entry point ("package.module:Class"), with clear errors."""

from __future__ import annotations

import importlib.util

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


@pytest.mark.parametrize(
    ("old", "new"),
    [
        # an old module path
        ("workers.envs.tabletop:TabletopEnv", "workers.envs.suites.tabletop.env:TabletopEnv"),
        # an old module path and an old class name
        (
            "workers.backbones.remote.client:RemoteBackbone",
            "workers.backbones.websocket.client:WebsocketBackbone",
        ),
        # an old class name in its present module
        ("workers.envs.server.client:RemoteEnv", "workers.envs.server.client:EnvServerClient"),
        # the old module, a package now that does not hold the class
        ("workers.envs.server:EnvServer", "workers.envs.server.serve:EnvServer"),
    ],
)
def test_an_entry_point_of_the_flat_layout_is_refused_naming_the_new_one(old, new) -> None:
    """One error naming the field and the name to write; no warning, no remap."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=rf"env\.suite={old!r} .*write env\.suite: {new}"):
            load_class({}, old, "env.suite")


def test_the_refusal_never_touches_a_present_path_and_names_modules_that_exist() -> None:
    """Each old module is gone (the package ``workers.envs.server`` aside) and each new one is
    there, so the refusal's name is one to write."""
    from workers.envs.server.client import EnvServerClient
    from workers.registry import MOVED_MODULES

    assert load_class({}, "workers.envs.server.client:EnvServerClient", "x") is EnvServerClient
    with pytest.raises(ValueError, match=r"module 'tests.doubles.envs' has no 'RemoteEnv'$"):
        load_class({}, "tests.doubles.envs:RemoteEnv", "env.suite")  # not ours to rename
    for old, new in MOVED_MODULES.items():
        assert importlib.util.find_spec(new) is not None, new
        assert (importlib.util.find_spec(old) is None) == (old != "workers.envs.server"), old
