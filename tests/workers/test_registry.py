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
        ("workers.episode:EpisodeSpec", "workers.episode.rows:EpisodeSpec"),
        # workers/ in rooms: the episode side and the policy side
        ("workers.actor:EpisodeWorker", "workers.episode.worker:EpisodeWorker"),
        ("workers.idr_wrapper:IDRWrapper", "workers.policy.wrapper:IDRWrapper"),
        ("workers.policy_actor:RemotePolicy", "workers.policy.actor:PolicyServiceClient"),
        # a module split in two or more: each class where it went
        ("workers.policy_socket:SocketToken", "workers.policy.socket_settings:SocketToken"),
        (
            "workers.policy_socket:PolicySocketConnection",
            "workers.policy.socket_client:PolicySocketConnection",
        ),
        (
            "workers.policy_socket:PolicySocketServer",
            "workers.policy.socket_server:PolicySocketServer",
        ),
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
    """Each old module is gone (the packages ``workers.envs.server`` and ``workers.episode``
    aside) and each new one is there, so the refusal's name is one to write; each class of a
    split module is in the module it is sent to."""
    from workers.envs.server.client import EnvServerClient
    from workers.registry import MOVED_CLASSES, MOVED_MODULES

    assert load_class({}, "workers.envs.server.client:EnvServerClient", "x") is EnvServerClient
    with pytest.raises(ValueError, match=r"module 'tests.doubles.envs' has no 'RemoteEnv'$"):
        load_class({}, "tests.doubles.envs:RemoteEnv", "env.suite")  # not ours to rename
    for old, new in MOVED_MODULES.items():
        assert importlib.util.find_spec(new) is not None, new
        packages_now = {"workers.envs.server", "workers.episode"}
        assert (importlib.util.find_spec(old) is None) == (old not in packages_now), old
    for old, new in MOVED_CLASSES.items():
        assert old.partition(":")[0] in MOVED_MODULES, old
        assert hasattr(importlib.import_module(new), old.partition(":")[2]), (old, new)
