"""Each suite's env.params as a typed model: the constructor's signature, checked before any
work, documented in the docs' tables."""

from __future__ import annotations

import pytest

from workers.envs.factory import ENVS, env_class
from workers.params_model import check_params, param_docs, params_model


@pytest.mark.parametrize("suite", sorted(ENVS))
def test_every_suite_has_a_model_and_documents_every_param(suite) -> None:
    cls = env_class(suite)
    model = params_model(cls)
    rows = param_docs(cls)
    assert [r.name for r in rows] == list(model.model_fields)
    assert all(r.doc and r.type for r in rows), [r.name for r in rows if not r.doc]


@pytest.mark.parametrize(
    ("suite", "params", "message"),
    [
        ("tabletop", {"image_sze": 64}, r"'image_sze': did you mean 'image_size'\?"),
        ("tabletop", {"image_size": "big"}, r"image_size='big' is invalid"),
        ("tabletop", {"subtask_budget": [1]}, r"subtask_budget=\[1\] is invalid"),
        # LIBERO-PRO passes its other params to LIBERO's env: checked against those
        ("libero_pro", {"lazy_rendr": False}, r"'lazy_rendr': did you mean 'lazy_render'\?"),
        ("gymnasium", {"id": "x", "succes_key": "ok"}, r"did you mean 'success_key'\?"),
        ("gymnasium", {}, r"id is required"),
    ],
)
def test_a_bad_param_is_one_error_naming_it(suite, params, message) -> None:
    with pytest.raises(ValueError, match=message):
        check_params(f"env.params (suite {suite!r})", env_class(suite), params)


def test_good_params_pass_as_written() -> None:
    """A YAML list for a tuple, a forwarded LIBERO param, lerobot config keys (checked by
    lerobot's config, not here)."""
    check_params("env.params", env_class("tabletop"), {"cameras": ["wrist"], "state_dims": [0]})
    check_params("env.params", env_class("libero_pro"), {"protocol": "lerobot", "image_size": 3})
    check_params("env.params", env_class("lerobot"), {"type": "pusht", "episode_length": 9})


def test_a_lerobot_config_key_is_checked_against_that_config() -> None:
    from workers.envs.suites.lerobot_envs.env import env_config

    with pytest.raises(ValueError, match=r"'episode_lenght': did you mean 'episode_length'\?"):
        env_config("pusht", {"episode_lenght": 3})
    assert env_config("pusht", {"episode_length": 3}).episode_length == 3


def test_the_docs_table_is_the_signature() -> None:
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "docs" / "hooks"))
    try:
        from params_tables import render
    finally:
        sys.path.pop(0)
    table = render("tabletop").splitlines()
    assert len(table) == 2 + len(param_docs(env_class("tabletop")))
    assert "| `subtask_budget` | `int` | `200` |" in "\n".join(table)
    assert "any other" in render("lerobot") and "any other" not in render("libero_pro")
