"""Fault-injecting env doubles: the fake marker env with faults placed by episode index."""

from __future__ import annotations

import os
from dataclasses import replace

from tests.doubles import faults
from workers.envs.base import EnvObservation, TaskSpec, checked_action
from workers.envs.fakes import FakeMarkerEnv


class FaultyMarkerEnv(FakeMarkerEnv):
    """FakeMarkerEnv (suite ``fake_marker``) that fails on purpose, by episode index.

    In reset: ``fail_once`` raises the first time in this process, ``fail_always`` every
    time, ``exit_on`` kills the process (a segfaulting simulator), ``hang_on`` never returns,
    ``oom_on`` allocates past an RLIMIT_AS ``memory_limit_mb`` above the process's size
    (MemoryError), ``oom_kill_on`` then SIGKILLs the process (as the OOM killer would);
    ``nan_state_on`` makes the state NaN from step 2 (an unstable simulation). The last four
    fire in every reset, or once per run with ``once_dir`` (see tests.doubles.faults)."""

    def __init__(
        self,
        image_size: int = 32,
        fail_once: tuple[int, ...] = (),
        fail_always: tuple[int, ...] = (),
        exit_on: tuple[int, ...] = (),
        hang_on: tuple[int, ...] = (),
        oom_on: tuple[int, ...] = (),
        oom_kill_on: tuple[int, ...] = (),
        memory_limit_mb: int = 64,
        nan_state_on: tuple[int, ...] = (),
        once_dir: str | None = None,
    ) -> None:
        super().__init__(image_size=image_size)
        self.fail_once, self.fail_always = set(fail_once), set(fail_always)
        self.exit_on, self.hang_on = set(exit_on), set(hang_on)
        self.oom_on, self.oom_kill_on = set(oom_on), set(oom_kill_on)
        self.nan_state_on, self.memory_limit_mb = set(nan_state_on), memory_limit_mb
        self.once_dir = once_dir
        self._nan_state = False
        self._failed: set[int] = set()

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        self._spec(task_id)
        if episode_index in self.exit_on:
            os._exit(17)
        if episode_index in self.fail_always or (
            episode_index in self.fail_once and episode_index not in self._failed
        ):
            self._failed.add(episode_index)
            raise RuntimeError(f"injected failure in reset of episode {episode_index}")
        fire = faults.should_fire
        if fire("hang", episode_index, self.hang_on, self.once_dir):
            faults.hang_forever()
        if fire("oom", episode_index, self.oom_on, self.once_dir):
            faults.exhaust_memory(self.memory_limit_mb)
        if fire("oom_kill", episode_index, self.oom_kill_on, self.once_dir):
            faults.exhaust_memory(self.memory_limit_mb, kill=True)
        self._nan_state = fire("nan_state", episode_index, self.nan_state_on, self.once_dir)
        return super().reset(task_id, episode_index, seed)

    def _observe(self) -> EnvObservation:
        obs = super()._observe()
        if self._nan_state and self._clock.steps >= 2:
            obs.state[:] = float("nan")
        return obs


class TwoSuiteMarkerEnv(FakeMarkerEnv):
    """FakeMarkerEnv whose two tasks belong to suites of their own (``marker_a``,
    ``marker_b``), as LIBERO's tasks belong to libero_spatial, libero_10, ... under one env."""

    @classmethod
    def suite_tasks(cls, **_: object) -> list[TaskSpec]:
        return [
            replace(t, suite=f"marker_{s}", name=f"{t.name} ({s})")
            for t, s in zip(FakeMarkerEnv.suite_tasks(), "ab", strict=True)
        ]

    def tasks(self) -> list[TaskSpec]:
        return self.suite_tasks()


class UnloadableMarkerEnv(FakeMarkerEnv):
    """Passes the pre-flight (its tasks are listed without building it) but cannot be built:
    a simulator that fails to start inside every worker."""

    def __init__(self, image_size: int = 32) -> None:
        raise RuntimeError("simulator cannot start: no rendering backend (injected)")


class ServerFaultEnv(FakeMarkerEnv):
    """FakeMarkerEnv for env-server tests, with faults placed by step inside the server
    process: ``exit_at_step`` kills the process at that step (a simulator that segfaults),
    ``hang_at_step`` never returns (a wedged one); with ``once_dir`` each fires once per test
    (a marker file), so the episode run again on a restarted server goes through.
    ``render_log`` appends each camera rendered to a file (lazy rendering seen from outside).
    ``check_runtime`` refuses ``missing_checkout`` as a real env refuses a missing checkout."""

    def __init__(
        self,
        image_size: int = 32,
        exit_at_step: int | None = None,
        hang_at_step: int | None = None,
        once_dir: str | None = None,
        render_log: str | None = None,
        missing_checkout: str | None = None,
    ) -> None:
        super().__init__(image_size=image_size)
        self.exit_at_step, self.hang_at_step = exit_at_step, hang_at_step
        self.once_dir, self.render_log = once_dir, render_log
        self.episode = -1

    @classmethod
    def check_runtime(cls, missing_checkout: str | None = None, **_: object) -> None:
        if missing_checkout is not None and not os.path.isdir(missing_checkout):
            raise ValueError(
                f"env.params.missing_checkout={missing_checkout}: no such checkout; point it at "
                "a clone of the fake"
            )

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        self.episode = episode_index
        return self._logged(super().reset(task_id, episode_index, seed))

    def step(self, action):  # type: ignore[no-untyped-def]
        if self._clock.steps + 1 == self.exit_at_step and faults.should_fire(
            "server_exit", self.episode, {self.episode}, self.once_dir
        ):
            os._exit(9)
        if self._clock.steps + 1 == self.hang_at_step and faults.should_fire(
            "server_hang", self.episode, {self.episode}, self.once_dir
        ):
            faults.hang_forever()
        return self._logged(super().step(action))

    def _logged(self, obs: EnvObservation) -> EnvObservation:
        if self.render_log is None:
            return obs
        log_path, images = self.render_log, obs.images

        class Logged(dict):  # type: ignore[type-arg]
            def __getitem__(self, cam: str):  # type: ignore[no-untyped-def]
                with open(log_path, "a") as f:
                    f.write(f"{cam}\n")
                return images[cam]

        return replace(obs, images=Logged.fromkeys(images))


class ChattyMarkerEnv(FakeMarkerEnv):
    """FakeMarkerEnv that talks as simulators do when built: a Python print, a library's
    logging warning and a C-level write to fd 2 (what robosuite and MuJoCo print)."""

    def __init__(self, image_size: int = 32) -> None:
        import logging
        import os

        super().__init__(image_size=image_size)
        print("chatty: python stdout line", flush=True)
        logging.getLogger("chatty_lib").warning("chatty: library warning")
        os.write(2, b"chatty: C-level stderr line\n")


class PropertyMarkerEnv(FakeMarkerEnv):
    """FakeMarkerEnv as a user's env written before the status record: its observations carry
    no status, which it keeps as properties (``task``, ``instruction``, ``success``,
    ``done``, ``subtasks_done``, ``steps``) and counts itself; read through the adapter
    (``workers.envs.base.episode_status``)."""

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        obs = super().reset(task_id, episode_index, seed)
        self._task, self._steps = self._clock.task, 0
        return replace(obs, status=None)

    def step(self, action):  # type: ignore[no-untyped-def]
        a = checked_action(
            action, self.action_dim, getattr(self, "_task", None) is not None, self.done
        )
        self._move(a)
        self._steps += 1
        return replace(self._observe(), status=None)

    @property
    def task(self) -> TaskSpec:
        if getattr(self, "_task", None) is None:
            raise RuntimeError("no task: call reset() first")
        return self._task

    @property
    def instruction(self) -> str:
        return self._INSTRUCTIONS[self.task.task_id]

    @property
    def success(self) -> bool:
        return (
            getattr(self, "_task", None) is not None
            and self._done_count == self.task.subtasks_total
        )

    @property
    def done(self) -> bool:
        return self.success or (
            getattr(self, "_task", None) is not None and self._steps >= self.task.max_steps
        )

    @property
    def subtasks_done(self) -> int:
        return self._done_count

    @property
    def steps(self) -> int:
        return self._steps


class NoHiddenRenderMarkerEnv(FakeMarkerEnv):
    """The fake marker env without an object-hidden render (a suite mode pcd cannot run on)."""

    renders_hidden_objects = False
