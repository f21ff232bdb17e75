"""Any lerobot ``PreTrainedPolicy`` checkpoint as a backbone, with its saved processors.

Loading: ``config.json`` names the policy type; the policy class comes from lerobot's registry
and its weights from ``model.safetensors`` (pickled weights are refused); the pre- and
post-processor pipelines come from ``policy_preprocessor.json`` / ``policy_postprocessor.json``.
A hub id works too where the machine reaches a hub or has it cached; here nothing downloads.

Inference calls ``predict_action_chunk`` directly (``select_action`` keeps action queues and,
for Diffusion, observation history, which three passes per step would corrupt).

Where the interventions happen (lerobot's conventions, see shared/notes/lerobot.md):
- do(V) on raw [0, 1] images before the preprocessor (the IDR wrapper does it): a black image
  for every family;
- do(S) by default after the normalizer (``state_space: normalized``: zero = the dataset mean),
  through an after-step hook on the preprocessor's normalizer step, so it happens before any
  later step (pi0.5's state tokenizer); ``raw`` zeroes the physical state before the pipeline.

Common random numbers: policies whose ``predict_action_chunk`` takes ``noise`` (pi0, pi0.5,
SmolVLA, Diffusion) get the same noise for the three thirds of one 3B forward; stochastic
policies without it (X-VLA, GR00T) run the three passes sequentially, each under a forked RNG
seeded identically; deterministic ones (ACT) need neither. ``crn_mode`` records which.
"""

from __future__ import annotations

import functools
import json
import os
import re
from pathlib import Path
from typing import Any, ClassVar

import torch
from idr_core.checkpoint import check_checkpoint_dir
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE, camera_of
from idr_core.interventions import intervene
from idr_core.plugins import import_error, policy_plugins
from idr_core.sampling import DETERMINISTIC_TYPES, crn_mode

from workers.backbones.base import HISTORY_IMAGES, HISTORY_STATE, Observation
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


def split_postprocessor(post: Any) -> tuple[Any, Any | None]:
    """``post`` as (its steps up to and including the action unnormalizer, the steps after it
    or None). IDR measures and refines physical actions, as the plugin's
    ``refine_space=physical`` does; a step after the unnormalizer that changes values
    (VLA-JEPA binarizes its gripper) then applies to the refined chunk the env executes, not
    to the three passes. Device moves after it are kept in the first part: they change no
    value."""
    from lerobot.processor import DeviceProcessorStep, PolicyProcessorPipeline

    names = [type(s).__name__ for s in post.steps]
    if "UnnormalizerProcessorStep" not in names:
        return post, None
    cut = names.index("UnnormalizerProcessorStep") + 1
    after = post.steps[cut:]
    if all(isinstance(s, DeviceProcessorStep) for s in after):
        return post, None

    def part(steps: list[Any], name: str) -> Any:
        return PolicyProcessorPipeline(
            steps=steps,
            name=name,
            to_transition=post.to_transition,
            to_output=post.to_output,
        )

    return part(post.steps[:cut], f"{post.name}_physical"), part(after, f"{post.name}_finish")


class LerobotBackbone:
    """A lerobot policy checkpoint behind the Backbone protocol."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset({"normalized"})

    @classmethod
    def check_params(cls, params: dict[str, Any]) -> None:
        if "path" not in params:
            raise ValueError(
                "backbone.params.path is required: a lerobot checkpoint folder or hub id"
            )
        check_checkpoint(str(params["path"]), bool(params.get("allow_download", False)))

    @classmethod
    def describe(cls, params: dict[str, Any]) -> PolicyIO | None:
        """The checkpoint's inputs and outputs from its config.json (no weights, no GPU);
        None for a hub id, which is not on this machine to read."""
        path = check_checkpoint(str(params["path"]), bool(params.get("allow_download", False)))
        return None if path is None else policy_io(path, params.get("chunk_len"))

    def __init__(
        self,
        path: str,
        device: str = "cpu",
        camera_map: dict[str, str] | None = None,
        chunk_len: int | None = None,
        allow_download: bool = False,
    ) -> None:
        """``camera_map``: env camera -> policy image key suffix (``observation.images.<suffix>``).
        A run fills it in on the driver from the env's cameras and the names checkpoints give
        them (``workers.io_spec``: LIBERO's ``image`` / ``image2`` ...); give it for a checkpoint
        whose names no convention covers. Default here: the same names.
        ``allow_download``: a hub id may be fetched (off by default: runs are offline)."""
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        register_project_policies()
        check_checkpoint(path, allow_download)
        self.path = path
        self.device = torch.device(device)
        cfg = PreTrainedConfig.from_pretrained(path)
        cfg.device = str(self.device)
        cfg.pretrained_path = Path(path)  # as lerobot's CLIs: EO1 builds its VLM from its config
        self.config = cfg
        self.policy = (
            get_policy_class(cfg.type).from_pretrained(path, config=cfg).to(self.device).eval()
        )
        # the device step runs where the policy runs, whatever device it was trained on (a
        # checkpoint saved on a GPU names cuda), as lerobot-eval overrides it
        overrides = {"device_processor": {"device": str(self.device)}}
        pre, post = make_pre_post_processors(
            cfg, pretrained_path=path, preprocessor_overrides=overrides
        )
        self._adopt(pre, post, camera_map, chunk_len)

    def _adopt(
        self, pre: Any, post: Any, camera_map: dict[str, str] | None, chunk_len: int | None
    ) -> None:
        """What the backbone reads of ``self.policy`` and ``self.config`` and the processors
        (loaded from a folder here, given by a caller with a policy in memory:
        ``pipeline.api``)."""
        cfg = self.config
        self.pre = pre
        self.post, self.finish_chunk = split_postprocessor(post)
        from lerobot_policy_idr.runtime import action_bounds

        # refined chunks are clipped into these (idr.clip_actions), as the idr policy clips
        self.action_bounds = action_bounds(self.post.steps)
        self.name = f"lerobot:{cfg.type}"
        image_keys = [k for k in cfg.input_features if camera_of(k) is not None]
        self._image_key = {str(camera_of(k)): k for k in image_keys}  # suffix -> policy key
        mapping = camera_map or {s: s for s in self._image_key}
        wanted = {self._image_key.get(v, IMAGE_PREFIX + v) for v in mapping.values()}
        if wanted != set(image_keys):
            raise ValueError(
                f"backbone.params.camera_map={mapping} gives policy image keys {sorted(wanted)}, "
                f"but the checkpoint's config.json declares {sorted(image_keys)}: map each env "
                "camera to one of them"
            )
        self.camera_map = mapping
        self.cameras = tuple(mapping)  # env cameras to render
        self.image_shapes = {k: tuple(cfg.input_features[k].shape) for k in image_keys}
        # a policy that resizes its images (RESIZE_KEYS) takes any size of its channel count
        self.resizes_images = any(getattr(cfg, k, None) for k in RESIZE_KEYS)
        state = cfg.input_features.get(OBS_STATE)
        self.state_dim = int(state.shape[0]) if state is not None else 0
        self.action_dim = int(cfg.output_features[ACTION].shape[0])
        self.chunk_len = int(
            chunk_len
            or getattr(cfg, "n_action_steps", None)
            or getattr(cfg, "chunk_size", None)
            or cfg.action_chunk_size  # VQ-BeT executes its whole chunk
        )
        from lerobot_policy_idr.runtime import history_length

        # frames one inference reads (Diffusion's n_obs_steps...): the episode loop sends the
        # past ones with each request
        self.history_steps = history_length(cfg)
        self.crn_mode = crn_mode(cfg.type, self.policy.predict_action_chunk)
        self.can_batch = (
            self.crn_mode != "seeded_rng"
        )  # one seed cannot give three thirds equal noise
        self._normalizer_index = self._find_normalizer()
        from lerobot_policy_idr.runtime import state_mean

        # do(S) under state_space=centered: about the dataset mean state, in physical units
        state_feature = cfg.input_features.get(OBS_STATE)
        self.state_mean = (
            state_mean(self.pre.steps, int(state_feature.shape[0])) if state_feature else None
        )
        self._pending_do: tuple[torch.Tensor, Any] | None = None
        self.pre.register_after_step_hook(self._state_intervention_hook)

    def _find_normalizer(self) -> int | None:
        for i, step in enumerate(self.pre.steps):
            if type(step).__name__ == "NormalizerProcessorStep":
                return i
        return None

    def _state_intervention_hook(self, index: int, transition: Any) -> None:
        """After the normalizer: do(S) on the flagged rows, in normalized space."""
        if self._pending_do is None or index != self._normalizer_index:
            return
        from lerobot.lerobot_types import TransitionKey

        rows, iv = self._pending_do
        obs = transition[TransitionKey.OBSERVATION]
        state = obs[OBS_STATE]
        cf = intervene(state, iv.strategy, noise_scale=iv.noise_scale, seed=iv.seed)
        obs[OBS_STATE] = torch.where(rows.to(state.device)[:, None], cf, state)

    # -- protocol ---------------------------------------------------------------------------
    def reset(self) -> None:
        self.policy.reset()

    def make_noise(self, batch_size: int, seed: int) -> Any:
        """The step's noise from its seed, drawn as the idr policy draws it from one
        (``runtime.step_noise``)."""
        from lerobot_policy_idr.runtime import step_noise

        return step_noise(
            self.config, self.crn_mode, batch_size, self.action_dim, seed, self.device
        )

    def _batch(self, obs: Observation) -> dict[str, Any]:
        batch: dict[str, Any] = {}
        for env_cam, key in self.camera_map.items():
            if env_cam not in obs.images:
                raise ValueError(
                    f"the policy needs camera {env_cam!r}; the observation has {list(obs.images)}"
                )
            img = torch.as_tensor(obs.images[env_cam]).float()
            policy_key = self._image_key[key]
            want = self.image_shapes[policy_key]
            got = tuple(img.shape[1:])
            if got != want and (not self.resizes_images or got[0] != want[0]):
                raise ValueError(
                    f"camera {env_cam!r} gives images {got}, policy key "
                    f"{policy_key!r} expects {want}: set env.params.image_size to match"
                )
            batch[policy_key] = img
        if self.state_dim:
            state = torch.as_tensor(obs.state).float()
            if state.shape[1] != self.state_dim:
                raise ValueError(
                    f"env state has {state.shape[1]} dims, policy {OBS_STATE!r} expects {self.state_dim}"
                )
            batch[OBS_STATE] = state
        batch["task"] = list(obs.instruction)
        return batch

    def _frames(self, obs: Observation, batch: dict[str, Any]) -> list[dict[str, Any]]:
        """The episode's frames that a history-fed base reads, oldest first, the current last:
        the past ones travel with the request (``Observation.extras``, ``HISTORY_IMAGES`` /
        ``HISTORY_STATE``: the service stays a pure function of each request), each made a
        batch as the current one is."""
        images = obs.extras.get(HISTORY_IMAGES)
        if not images:
            return [batch]
        state = obs.extras.get(HISTORY_STATE)
        k = next(iter(images.values())).shape[1]
        past = [
            self._batch(
                Observation(
                    {cam: x[:, i] for cam, x in images.items()},
                    state[:, i] if state is not None else obs.state,
                    list(obs.instruction),
                )
            )
            for i in range(k)
        ]
        return [*past, batch]

    @torch.inference_mode()
    def predict_chunk(
        self, obs: Observation, noise: Any = None, intervention: Any = None
    ) -> torch.Tensor:
        batch = self._batch(obs)
        if obs.do_image is not None and obs.do_image.any():
            raise ValueError(
                "image interventions apply in raw space (before the preprocessor) for lerobot policies"
            )
        if obs.do_state is not None and obs.do_state.any():
            if self._normalizer_index is None:
                raise ValueError(
                    f"{self.name}: no normalizer step in the preprocessor for state_space=normalized"
                )
            self._pending_do = (torch.as_tensor(obs.do_state), intervention)
        try:  # each frame through the preprocessor, do(S) on the flagged rows of every frame
            frames = [self.pre(f) for f in self._frames(obs, batch)]
        finally:
            self._pending_do = None
        from lerobot_policy_idr.runtime import base_input

        # what the base reads of the frames, as the idr policy builds it
        processed, lent = base_input(self.config, getattr(self.policy, "_queues", None), frames)
        from lerobot_policy_idr.modeling_idr import weights_version

        version = weights_version(self.policy)
        own = getattr(self.policy, "_queues", None)
        if lent is not None:
            self.policy._queues = lent
        try:
            if self.crn_mode == "shared_noise" and noise is not None:
                actions = self.policy.predict_action_chunk(processed, noise=noise)
            elif self.crn_mode == "seeded_rng" and noise is not None:
                devices = [self.device] if self.device.type == "cuda" else []
                with torch.random.fork_rng(devices=devices):
                    torch.manual_seed(int(noise[0]))
                    actions = self.policy.predict_action_chunk(processed)
            else:
                actions = self.policy.predict_action_chunk(processed)
        finally:
            if lent is not None:
                self.policy._queues = own
        if weights_version(self.policy) != version:
            raise ValueError(
                f"{self.name} changed its own weights during predict_action_chunk (test-time "
                "training?): the grid's cells must run one frozen network, and IDR's "
                "counterfactual rows would train it; turn the policy's adaptation off"
            )
        return self.post(actions)[:, : self.chunk_len]
