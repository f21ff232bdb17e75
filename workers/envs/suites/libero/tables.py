"""LIBERO's benchmark tables (hf-libero): the suites' tasks, their fixed init states and the
assets check, without a simulator (MuJoCo is not imported here).
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
from pathlib import Path
from typing import Any

import numpy as np

from workers.envs.base import TaskSpec
from workers.envs.suites.libero.assets import LiberoSetupError, ensure_config_env
from workers.envs.suites.libero.protocol import LiberoProtocol

SETUP_COMMAND = "python -m workers.envs.suites.libero.assets"


def _benchmark_module() -> Any:
    """``libero.libero.benchmark``, imported only after its config is in place (never prompts)."""
    ensure_config_env()
    from libero.libero import benchmark

    return benchmark


@functools.cache
def benchmark_suite(name: str) -> Any:
    """The suite's Benchmark object (task table; no simulator). Its constructor prints the task
    order on every call: built once per process, quietly."""
    with contextlib.redirect_stdout(io.StringIO()):
        return _benchmark_module().get_benchmark(name)()


def fixed_init_states(bench: Any, index: int) -> np.ndarray:
    """The task's fixed init states, as hf-libero's ``get_task_init_states`` finds them but
    loaded without running pickled code (hf-libero unpickles them with weights_only=False)."""
    from libero.libero import get_libero_path

    from workers.safe_load import load_numpy_array

    task = bench.get_task(index)
    path = os.path.join(get_libero_path("init_states"), task.problem_folder, task.init_states_file)
    return load_numpy_array(path)


def list_tasks(protocol: LiberoProtocol) -> list[TaskSpec]:
    """The tasks of the protocol's suites, in each suite's default order."""
    ensure_config_env()  # every time: the suite tables below are cached per process
    return [
        TaskSpec(
            task_id=f"{suite}/{i}",
            name=task.name,
            max_steps=protocol.max_steps[suite],
            suite=suite,
            instruction=task.language,
        )
        for suite in protocol.suites
        for i, task in enumerate(benchmark_suite(suite).tasks)
    ]


def check_assets() -> None:
    """hf-libero downloads its assets when ``libero/libero/assets`` is absent: refuse instead."""
    ensure_config_env()
    import libero.libero

    scenes = Path(libero.libero.__file__).parent / "assets" / "scenes"
    if not scenes.is_dir():
        raise LiberoSetupError(
            f"LIBERO assets are missing ({scenes} not found) and nothing may download: "
            f"run `{SETUP_COMMAND}` (part of `make setup`)"
        )
