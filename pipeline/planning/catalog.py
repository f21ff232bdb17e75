"""What a config can name (``idr-eval list``): suites, lerobot env types with whether their
packages are installed here, a suite's tasks, perturbation kinds and which suites apply them,
backbones. Nothing is built but the env of ``tasks`` for a suite that cannot list its tasks
without one."""

from __future__ import annotations

import importlib.util
from typing import Any

from pipeline.errors import ConfigError

# the module each lerobot env type imports to build its env (lerobot's config names gym_<type>
# for the single-task ones; the multi-task ones import their own simulators)
ENV_TYPE_MODULES = {
    "libero": "libero",
    "libero_plus": "libero",
    "metaworld": "metaworld",
    "robocasa": "robocasa",
    "vlabench": "VLABench",
    "isaaclab_arena": "isaaclab",
    "robotwin": "robotwin",
    "robomme": "robomme",
    "gym_manipulator": "lerobot.rl",
}


def _first_line(cls: Any) -> str:
    doc = (cls.__doc__ or "").strip().splitlines()
    return doc[0] if doc else ""


def suites() -> list[tuple[str, str]]:
    """(name, what) of every registered suite; a suite whose module cannot be imported here
    says why."""
    from workers.envs.factory import ENVS, env_class

    out = []
    for name in ENVS:
        try:
            out.append((name, _first_line(env_class(name))))
        except Exception as exc:  # its simulator is absent here: say so, list the rest
            out.append((name, f"(not importable here: {exc})"))
    return out


def _installed(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False


def lerobot_env_types() -> list[tuple[str, str, bool, str]]:
    """(type, module it needs, installed here, note) for every env type lerobot registers; the
    note says which types were run here (docs/suites/lerobot.md) and which the suite refuses."""
    from workers.envs.suites.lerobot_envs.env import LIBERO_TYPES, RUN_HERE, known_types

    def note(t: str) -> str:
        if t in LIBERO_TYPES:
            return f"refused: {LIBERO_TYPES[t]}"
        return RUN_HERE.get(t, "not run here")

    return [
        (t, m, _installed(m), note(t))
        for t in known_types()
        for m in [ENV_TYPE_MODULES.get(t, f"gym_{t}")]
    ]


def perturbation_kinds() -> list[tuple[str, str, str]]:
    """(kind, what, where) of every perturbation kind."""
    from workers.envs.base import suite_info
    from workers.envs.factory import ENVS, env_class
    from workers.envs.wrappers.perturbation_grammar import KINDS

    by_kind: dict[str, list[str]] = {}
    for name in ENVS:
        try:
            for kind in suite_info(env_class(name)).perturbation_kinds:
                by_kind.setdefault(kind, []).append(name)
        except Exception:  # not importable here
            continue
    return [
        (
            kind,
            f"{k.what} ({k.low:g} < SEVERITY <= {k.high:g} {k.unit})",
            ", ".join(by_kind.get(kind, [])) if k.scene else "every suite",
        )
        for kind, k in KINDS.items()
    ]


def backbones() -> list[tuple[str, str]]:
    from workers.backbones.factory import BACKBONES

    return [(name, entry) for name, entry in BACKBONES.items()]


def suite_task_specs(suite: str, params: dict[str, Any], server: Any = None) -> list[Any]:
    """``suite``'s TaskSpecs (workers.envs.factory.suite_tasks); a suite that builds its env to
    list its tasks refuses bad params there, as a ValueError: a ConfigError here."""
    from workers.envs.factory import suite_tasks

    try:
        return suite_tasks(suite, params, server)
    except ConfigError:
        raise
    except ValueError as e:
        raise ConfigError(str(e)) from None


def tasks(suite: str, params: dict[str, Any]) -> list[tuple[str, str, int]]:
    """(task id, name, max steps) of ``suite`` built with ``params``."""
    return [(t.task_id, t.name, t.max_steps) for t in suite_task_specs(suite, params)]
