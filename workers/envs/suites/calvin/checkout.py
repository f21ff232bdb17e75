"""Where CALVIN's code lives on this machine: the calvin_env checkout (``env.params.calvin_env``
or ``$CALVIN_ENV``), the language annotations of the mees/calvin clone around it, its git
commit, and calvin_env's simulator and task oracle built from them (hydra, as the official
``get_env`` does). Nothing of theirs is imported until a simulator is built.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

ANNOTATIONS_IN_CALVIN = "calvin_models/conf/annotations/new_playtable_validation.yaml"
TASKS_IN_CALVIN_ENV = "conf/tasks/new_playtable_tasks.yaml"
# calvin_env commit that mees/calvin's submodule pins (since 2023-05) and that leaves the LED on
# when its button is pressed once at the start of a sequence (fixed in 797142c)
BUTTON_BUG_COMMIT = "1431a46"


# the config groups the env is composed from (config_data_collection.yaml's defaults, with the
# evaluation's cameras): a copy of the repository without them cannot build the env
CONF_NEEDED = (
    "config_data_collection.yaml",
    "env/play_table_env.yaml",
    "vr_input/vr_input.yaml",
    "cameras/static_and_gripper.yaml",
    "recorder/recorder.yaml",
    TASKS_IN_CALVIN_ENV.removeprefix("conf/"),
)


def find_checkout(calvin_env: str | None) -> Path:
    """The calvin_env checkout; ValueError naming the field and where to get one."""
    root = calvin_env or os.environ.get("CALVIN_ENV")
    if not root:
        raise ValueError(
            "env.params.calvin_env is not set and neither is $CALVIN_ENV: point either at a "
            "checkout of calvin_env (MIT, github.com/mees/calvin_env; as a submodule of "
            "`git clone --recurse-submodules https://github.com/mees/calvin`)"
        )
    path = Path(root).expanduser().resolve()
    if not (path / "calvin_env" / "envs" / "play_table_env.py").is_file():
        raise ValueError(
            f"env.params.calvin_env={root}: not a calvin_env checkout (no calvin_env/envs/"
            "play_table_env.py); point it at the calvin_env folder of a mees/calvin clone"
        )
    if lost := [c for c in CONF_NEEDED if not (path / "conf" / c).is_file()]:
        raise ValueError(
            f"env.params.calvin_env={root}: an incomplete calvin_env checkout, its conf/ lacks "
            f"{lost} (the env is composed from them); clone github.com/mees/calvin_env whole"
        )
    return path


def annotations_file(checkout: Path, annotations: str | None) -> Path:
    """The evaluation's language annotations: ``annotations``, else the mees/calvin clone's."""
    if annotations is not None:
        path = Path(annotations).expanduser()
        if not path.is_file():
            raise ValueError(f"env.params.annotations={annotations}: no such file")
        return path
    candidates = [checkout.parent / ANNOTATIONS_IN_CALVIN]
    if os.environ.get("CALVIN_ROOT"):
        candidates.insert(0, Path(os.environ["CALVIN_ROOT"]) / ANNOTATIONS_IN_CALVIN)
    for path in candidates:
        if path.is_file():
            return path
    raise ValueError(
        f"the language annotations of the evaluation ({ANNOTATIONS_IN_CALVIN}) are not in the "
        f"mees/calvin checkout around {checkout}: set env.params.annotations to that file, or "
        "$CALVIN_ROOT to the mees/calvin clone"
    )


def checkout_commit(checkout: Path) -> str | None:
    """The checkout's git commit, or None (not a git clone, or no git)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(checkout), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def load_annotations(path: Path) -> dict[str, str]:
    """Subtask -> the instruction of the evaluation (the first of its annotations)."""
    from omegaconf import OmegaConf

    return {task: str(texts[0]) for task, texts in OmegaConf.load(path).items()}


def build_play_table(checkout: Path, scene: str, robot: str, renderer: str) -> Any:
    """calvin_env's PlayTableSimEnv, composed from its own conf/ as the dataset's
    merged_config.yaml was, and instantiated as the official ``get_env`` does."""
    if str(checkout) not in sys.path:
        sys.path.insert(0, str(checkout))
    import calvin_env.envs.play_table_env as play_table_env
    import hydra
    from hydra.core.global_hydra import GlobalHydra

    original = play_table_env.get_git_commit_hash
    if not getattr(original, "idr_wrapped", False):

        def commit_or_unknown(path: Any) -> str:  # it raises outside a git clone
            try:
                return original(path)
            except Exception:
                return "unknown"

        commit_or_unknown.idr_wrapped = True  # type: ignore[attr-defined]
        play_table_env.get_git_commit_hash = commit_or_unknown
    overrides = [
        "hydra/job_logging=default",  # its colorlog needs a plugin the eval does not
        "hydra/hydra_logging=default",
        "cameras=static_and_gripper",
        f"scene={scene}",
        f"robot={robot}",
        "use_vr=false",
        f"env.use_egl={str(renderer == 'egl').lower()}",
        "env.show_gui=false",
        "env.use_scene_info=true",
    ]
    GlobalHydra.instance().clear()
    with hydra.initialize_config_dir(config_dir=str(checkout / "conf"), version_base=None):
        cfg = hydra.compose(config_name="config_data_collection", overrides=overrides)
    try:  # as the official get_env instantiates the dataset's merged config
        return hydra.utils.instantiate(cfg.env, show_gui=False, use_vr=False, use_scene_info=True)
    except SystemExit:  # calvin_env exits when the EGL plugin does not load
        raise RuntimeError(
            "PyBullet's EGL renderer plugin did not load here: install an EGL driver (a GPU's, "
            "or Mesa's libegl1), or set env.params.renderer=tiny (CPU renderer, other pixels)"
        ) from None


def build_oracle(checkout: Path) -> Any:
    """calvin_env's task oracle of the evaluation (``new_playtable_tasks.yaml``)."""
    import hydra
    from omegaconf import OmegaConf

    return hydra.utils.instantiate(OmegaConf.load(checkout / TASKS_IN_CALVIN_ENV))
