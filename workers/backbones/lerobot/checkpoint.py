"""A lerobot checkpoint folder read without loading its policy: what the pre-flight and the
planning need (its inputs and outputs, its dataset's mean state, its policy type and the plugin
that provides it, a rebuild hint for a folder not built yet). ``adapter`` loads the policy."""

from __future__ import annotations

import functools
import json
import os
import re
from pathlib import Path

from idr_core.checkpoint import check_checkpoint_dir
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE, camera_of
from idr_core.plugins import import_error, policy_plugins
from idr_core.sampling import DETERMINISTIC_TYPES

from workers.io_spec import PolicyIO

# config.json keys by which a policy resizes its images to its own resolution (pi0, pi0.5,
# pi0-FAST, SmolVLA, X-VLA, Diffusion's resize_shape...): any rendered size then fits it.
RESIZE_KEYS = (
    "image_resolution",
    "resize_imgs_with_padding",
    "resize_shape",
    "image_resize_shape",
    "resize_images_to",
)


def _is_local(path: str) -> bool:
    return path.startswith((".", "/", "~")) or os.path.exists(path) or path.count("/") != 1


REBUILD_FILE = "REBUILD.json"


def rebuild_hint(missing: Path) -> str:
    """How to rebuild a missing checkpoint, where the folder meant to hold it says so: a
    ``REBUILD.json`` beside it mapping folder names to commands (checkpoints/zoo has one: its
    members are not all shipped in git)."""
    import json

    index = missing.parent / REBUILD_FILE
    try:
        commands = json.loads(index.read_text())
    except (OSError, ValueError):
        return ""
    command = commands.get(missing.name) if isinstance(commands, dict) else None
    return f"; rebuild it with: {command}" if isinstance(command, str) else ""


def check_checkpoint(path: str, allow_download: bool = False) -> Path | None:
    """Refuse, on the driver and before any actor starts, a checkpoint that does not exist, is
    not a lerobot policy of a known type, or whose weights are not a complete safetensors file
    (header and sizes checked; no tensor is loaded, no pickle is ever opened).

    Returns the local directory, or None for a hub id (only with ``allow_download``)."""
    if not _is_local(path):
        if allow_download:
            return None
        raise ValueError(
            f"backbone.params.path={path!r} looks like a hub id: not downloadable here (runs are "
            "offline); download the checkpoint beforehand and give its local folder, or set "
            "backbone.params.allow_download=true where the hub is reachable"
        )
    p = Path(path).expanduser()
    if not p.is_dir():
        raise ValueError(
            f"backbone.params.path={path!r} does not exist (a checkpoint folder or a hub id)"
            + rebuild_hint(p)
        )
    kind = check_checkpoint_dir(p, "backbone.params.path", known_policy_types())["type"]
    check_plugin_imports(str(kind))
    return p


def _shape(cfg_path: Path, key: str, feature: object) -> tuple[int, ...]:
    shape = feature.get("shape") if isinstance(feature, dict) else None
    if not isinstance(shape, list) or not all(isinstance(d, int) and d > 0 for d in shape):
        raise ValueError(
            f"{cfg_path}: {key!r} has no valid shape ({feature!r}); a lerobot config.json "
            "gives each feature {'type': ..., 'shape': [...]}"
        )
    return tuple(shape)


def policy_io(path: Path, chunk_len: int | None = None) -> PolicyIO:
    """What the checkpoint in ``path`` reads and writes, from its config.json alone."""
    cfg_path = path / "config.json"
    cfg = json.loads(cfg_path.read_text())
    inputs, outputs = cfg.get("input_features"), cfg.get("output_features")
    if not isinstance(inputs, dict) or not isinstance(outputs, dict) or ACTION not in outputs:
        raise ValueError(
            f"backbone.params.path={str(path)!r}: config.json lacks input_features / "
            "output_features.action, so what the policy reads cannot be checked"
        )
    images = {
        suffix: _shape(cfg_path, k, f)
        for k, f in inputs.items()
        if (suffix := camera_of(k)) is not None
    }
    for key, shape in images.items():
        if len(shape) != 3:
            raise ValueError(f"{cfg_path}: {IMAGE_PREFIX + key} shape {shape} is not (C, H, W)")
    state = inputs.get(OBS_STATE)
    steps = (
        chunk_len
        or cfg.get("n_action_steps")
        or cfg.get("chunk_size")
        or cfg.get("action_chunk_size")  # VQ-BeT
        or 1
    )
    dim = _shape(cfg_path, OBS_STATE, state)[0] if state is not None else None
    mean, mean_source = saved_state_mean(path, dim) if dim is not None else (None, None)
    return PolicyIO(
        images=images,
        state_dim=_shape(cfg_path, OBS_STATE, state)[0] if state is not None else None,
        action_dim=_shape(cfg_path, ACTION, outputs[ACTION])[0],
        chunk_len=int(steps),
        resizes_images=any(cfg.get(k) for k in RESIZE_KEYS),
        source=f"{cfg_path} (policy type {cfg.get('type')!r})",
        samples=cfg.get("type") not in DETERMINISTIC_TYPES,
        state_mean=mean,
        state_mean_source=mean_source,
        trained_on_data=True,
    )


def saved_state_mean(path: Path, dim: int) -> tuple[tuple[float, ...] | None, str | None]:
    """The mean of ``observation.state`` in the checkpoint's saved preprocessor normalizer
    (the first normalizer step's state file), read without torch; (None, None) where there is
    none. The same values the loaded normalizer subtracts (``runtime.state_mean``: the leading
    ``dim`` of statistics of a padded state)."""
    from safetensors.numpy import load_file

    pre = path / "policy_preprocessor.json"
    if not pre.is_file():
        return None, None
    steps = json.loads(pre.read_text()).get("steps") or []
    for step in steps:
        if step.get("registry_name") != "normalizer_processor" or not step.get("state_file"):
            continue
        stats_file = path / step["state_file"]
        if not stats_file.is_file():
            return None, None
        mean = load_file(str(stats_file)).get(f"{OBS_STATE}.mean")
        flat = mean.reshape(-1) if mean is not None else None
        if flat is None or len(flat) < dim:
            return None, None
        return tuple(float(v) for v in flat[:dim]), str(stats_file)
    return None, None


_REGISTER = re.compile(r"@PreTrainedConfig\.register_subclass\(\s*[\"']([\w.-]+)[\"']")


def policy_types_by_package() -> dict[str, set[str]]:
    """The policy types each package registers (lerobot's own policies, the project's plugin,
    each installed ``lerobot_policy_*`` plugin, found by lerobot's own rule), read from its
    config modules' source without importing it: importing lerobot's policies costs 20-35 s on
    a 2-core machine, too much for a pre-flight (the actors pay it once)."""
    import importlib.util

    found: dict[str, set[str]] = {}
    for package in ("lerobot.policies", "lerobot_policy_idr", *policy_plugins()):
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            continue
        types = found.setdefault(package, set())
        for root in spec.submodule_search_locations:
            for f in Path(root).glob("**/configuration_*.py"):
                types.update(_REGISTER.findall(f.read_text(errors="replace")))
    return found


def known_policy_types() -> set[str]:
    """Policy types lerobot's config registry holds, the project's own (tiny_vla) and installed
    plugins' included (``policy_types_by_package``). Empty when lerobot's layout is not the
    expected one (the check is then skipped)."""
    return set().union(*policy_types_by_package().values())


def check_plugin_imports(kind: str, field: str = "backbone.params.path") -> None:
    """A type that only a third-party plugin registers needs that plugin to import in the
    actors: import it here, on the driver, and refuse with the plugin's own error."""
    owners = policy_types_by_package()
    if any(kind in owners.get(p, ()) for p in ("lerobot.policies", "lerobot_policy_idr")):
        return
    for package, types in owners.items():
        if kind in types and (err := import_error(package)) is not None:
            raise ValueError(
                f"{field}: policy type {kind!r} comes from the plugin {package!r}, which fails "
                f"to import: {err}; fix or reinstall that plugin"
            )


@functools.cache
def register_project_policies() -> None:
    """Make the project's own lerobot policy types (tiny_vla, idr) and those of installed
    third-party plugins known to lerobot's registry, as lerobot's CLIs do at start."""
    from lerobot.utils.import_utils import register_third_party_plugins

    import lerobot_policy_idr  # noqa: F401

    register_third_party_plugins()
