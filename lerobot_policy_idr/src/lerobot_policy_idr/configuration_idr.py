"""The lerobot policy config of IDR, registered as policy type ``idr``.

An ``idr`` policy names a base policy (a lerobot checkpoint folder: act, diffusion, pi0, pi05,
smolvla, xvla, tiny_vla, or a type of a third-party ``lerobot_policy_*`` plugin) and IDR's
settings. lerobot resolves the policy class from this class's
name and module (``IDRConfig`` in ``configuration_idr`` -> ``modeling_idr.IDRPolicy``) and the
processors from ``processor_idr.make_idr_pre_post_processors``.

Two ways to run it, both with lerobot's own tools:
- ``--policy.path=<IDR folder>`` (made by ``lerobot-idr-wrap``): config.json of type ``idr``,
  the base's processors with IDR's two steps inserted, the base referenced by path (relative
  paths resolve against the folder; ``base/`` when the base is bundled);
- ``--policy.type=idr --policy.base_policy_path=<base folder>`` (processors built at start).
"""

from __future__ import annotations

import difflib
import functools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from idr_core.checkpoint import WEIGHTS, check_checkpoint_dir, sha256_file
from idr_core.features import ACTION, OBS_STATE, is_image_key
from idr_core.interventions import SPACES, STRATEGIES, InterventionConfig
from idr_core.methods import passes, refusal
from idr_core.plugins import describe_failures, plugin_import_errors
from idr_core.refiner import MODES, RefinerConfig
from idr_core.sampling import DETERMINISTIC_TYPES
from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import FeatureType, PolicyFeature

#: Base policy types IDR wraps, and why lerobot's others are refused (each reason verified on
#: lerobot 0.6.1 offline: docs/policy-types.md). A type registered by a third-party plugin
#: (a ``lerobot_policy_*`` distribution) takes the generic path (``is_third_party_type``).
SUPPORTED_BASE_TYPES = (
    "act",
    "diffusion",
    "pi0",
    "pi05",
    "smolvla",
    "xvla",
    "vqbet",
    "multi_task_dit",
    "eo1",
    "evo1",
    "vla_jepa",
    "tiny_vla",
)
REFUSED_BASE_TYPES = {
    "idr": "an idr policy cannot wrap another idr policy; wrap its base instead",
    "groot": "GR00T loads its processors from the hub; not supported offline",
    "fastwam": "FastWAM builds Wan2.2's VAE from a hub id written into its code and UMT5-XXL "
    "from the hub; neither can be had offline",
    "gaussian_actor": "an RL actor with no predict_action_chunk (one action per step): IDR has "
    "no chunk to run its passes on",
    "lingbot_va": "LingBot-VA runs batch 1 and carries a KV cache across calls (counterfactual "
    "passes would write into it), reads no state, and loads Wan's VAE and UMT5 from the hub",
    "molmoact2": "MolmoAct2 constructs only from a full MolmoAct2 checkpoint folder (its hub "
    "snapshot)",
    "tdmpc": "TD-MPC is a state-based RL planner: its predict_action_chunk reads select_action's "
    "queues and keeps a CEM warm start between calls",
    "pi0_fast": "pi0-FAST's constructor loads its FAST action tokenizer with "
    "trust_remote_code from a hub repo (lerobot/fast-action-tokenizer), code on no package "
    "index; offline it fails: 'Failed to load required tokenizers for PI0FastPolicy "
    "initialization'",
    "wall_x": "WALL-OSS needs peft, torchdiffeq and qwen-vl-utils (not installed) and its "
    "checkpoint from the hub",
}
REFINE_SPACES = ("physical", "normalized")
#: modes of idr_core.methods that lerobot's tools cannot run through this policy, and why
PLUGIN_REFUSED_MODES = {
    "pcd": "the object-hidden contrast needs a simulator that renders the scene without the "
    "task's objects; on a robot there is no such render (idr-eval runs it: env.suite tabletop)",
}


class IDRConfigError(ValueError):
    """A refusal of an idr config or folder: one message naming the field and the fix."""


@PreTrainedConfig.register_subclass("idr")
@dataclass
class IDRConfig(PreTrainedConfig):
    """IDR around a frozen base policy: three passes (factual, image zeroed, state zeroed) in
    one batched forward with shared noise, a diagnosis of the step's visual reliance and a
    gated residual refinement (the paper's Method section; the equations are in
    ``idr_core.refiner``)."""

    # The base policy: a local lerobot checkpoint folder (config.json, model.safetensors and
    # its processors). Relative paths resolve against the IDR folder, else the working dir.
    base_policy_path: str | None = None
    # sha256 of the base's model.safetensors when the folder was made; loading refuses a base
    # whose weights changed since (None: not checked).
    base_weights_sha256: str | None = None

    # The refiner (paper defaults; tau has none: it is the mean E_img of the baseline, which
    # depends on the backbone and the action space; calibrate it with mode=diagnose).
    # baseline, diagnose, A-F (E: the full method), E's controls (random, shuffled,
    # scale_free), image guidance (cfg), sample ensembling (ensemble) or temporal ensembling
    # (temporal); idr_core.methods lists every mode
    mode: str = "E"
    guidance: str = "visual"  # which modality's effect drives the correction
    alpha: float = 0.08
    beta: float = 0.05
    lam: float = 0.1
    tau: float | None = None
    eps: float = 1e-6
    w: float = 0.08  # the guidance weight of mode cfg (a_base + w * d_img)
    samples: int = 3  # chunks mode ensemble averages, each under its own noise draw
    te_coeff: float = 0.01  # mode temporal's coefficient (lerobot's ACT default)

    # The interventions do(V) and do(S).
    intervention_strategy: str = "zero"  # zero (the paper's), mean, gaussian
    # do(S): ``centered`` on the physical state about the base's dataset mean (zero = that
    # mean, whatever the normalizer: the harness's default too), ``normalized`` after the
    # base's normalizer (before pi0.5's state tokenizer), or ``raw`` on the physical state
    # about the origin; do(V) is always on raw [0, 1] images (a black image for every family).
    state_space: str = "centered"
    noise_scale: float = 0.5  # gaussian strategy only
    intervention_seed: int = 0

    # Where the refinement happens: on physical actions (the base's unnormalizer is applied
    # first, so tau and lam keep their meaning in robot units), or on normalized ones.
    refine_space: str = "physical"
    # Actions executed per chunk (None: the base's n_action_steps).
    n_action_steps: int | None = None
    # Clip the refined action into the base's action bounds (the dataset min/max its stats
    # hold, widened to the base action itself); the sidecar counts clipped elements.
    clip_actions: bool = True
    # A chunk whose inference took longer executes the base action and says so (None: no
    # deadline).
    deadline_ms: float | None = None
    # Where the diagnostics sidecar (Parquet, one row per env per inference) goes; None:
    # ./idr_diagnostics/<time>-<pid> in the working dir, said at start.
    diagnostics_dir: str | None = None

    normalization_mapping: dict[str, str] = field(default_factory=dict)
    push_to_hub: bool = False  # an IDR folder references its base: nothing to push

    def __post_init__(self) -> None:
        super().__post_init__()
        self.refiner()  # field checks, with the refiner's own messages
        if self.intervention_strategy not in STRATEGIES:
            raise IDRConfigError(
                f"policy.intervention_strategy={self.intervention_strategy!r} is unknown; "
                f"use one of {STRATEGIES}"
            )
        if self.state_space not in SPACES:
            raise IDRConfigError(
                f"policy.state_space={self.state_space!r} is unknown; use one of {SPACES}"
            )
        if not self.noise_scale >= 0:
            raise IDRConfigError(f"policy.noise_scale={self.noise_scale} must be >= 0")
        if self.refine_space not in REFINE_SPACES:
            raise IDRConfigError(
                f"policy.refine_space={self.refine_space!r} is unknown; use one of {REFINE_SPACES}"
            )
        if self.n_action_steps is not None and self.n_action_steps < 1:
            raise IDRConfigError(f"policy.n_action_steps={self.n_action_steps} must be >= 1")
        if self.deadline_ms is not None and not self.deadline_ms > 0:
            raise IDRConfigError(f"policy.deadline_ms={self.deadline_ms} must be > 0 (or unset)")
        if not self.input_features and self.base_policy_path:
            base = Path(self.base_policy_path).expanduser()
            if (base / "config.json").is_file():
                self.copy_features(read_base_config(base))

    # -- what the rest of the package reads ----------------------------------------------
    def refiner(self) -> RefinerConfig:
        """The refiner's settings. A refining mode needs tau (no default: calibrate it)."""
        try:
            cfg = RefinerConfig(
                alpha=self.alpha,
                beta=self.beta,
                lam=self.lam,
                tau=math.inf if self.tau is None else self.tau,
                eps=self.eps,
                mode=self.mode,
                guidance=self.guidance,
                w=self.w,
                samples=self.samples,
                te_coeff=self.te_coeff,
                clip_actions=self.clip_actions,
            )
        except ValueError as e:
            raise IDRConfigError(str(e).replace("RefinerConfig.", "policy.")) from None
        if self.mode in PLUGIN_REFUSED_MODES:
            runs = ", ".join(m for m in MODES if m not in PLUGIN_REFUSED_MODES)
            raise IDRConfigError(
                f"policy.mode={self.mode!r}: {PLUGIN_REFUSED_MODES[self.mode]}; the idr policy "
                f"runs {runs}"
            )
        if cfg.gated and self.tau is None:
            raise IDRConfigError(
                f"policy.mode={self.mode!r} refines actions and needs policy.tau: run mode "
                "'diagnose' for a few rollouts and calibrate it (lerobot-idr-calibrate), or set "
                "--tau / --policy.tau (the paper: the baseline's mean E_img)"
            )
        return cfg

    def intervention(self) -> InterventionConfig:
        return InterventionConfig(
            strategy=self.intervention_strategy,
            image_space="raw",
            state_space=self.state_space,
            noise_scale=self.noise_scale,
            seed=self.intervention_seed,
        )

    def copy_features(self, base: dict) -> None:
        """Input and output features from the base's config.json."""
        self.input_features = _features(base.get("input_features") or {})
        self.output_features = _features(base.get("output_features") or {})

    def resolve_base(self, folder: str | Path | None = None) -> Path:
        """The base checkpoint folder, checked: relative paths resolve against the IDR folder
        (``folder``, else ``pretrained_path``), else the working dir; its type must be one IDR
        wraps, and its weights the ones recorded when the folder was made."""
        if not self.base_policy_path:
            raise IDRConfigError(
                "policy.base_policy_path is required: the lerobot checkpoint folder IDR wraps "
                "(--policy.base_policy_path=DIR, or make an IDR folder with lerobot-idr-wrap)"
            )
        base = Path(self.base_policy_path).expanduser()
        anchor = folder or self.pretrained_path
        if not base.is_absolute() and anchor and (Path(anchor) / base).is_dir():
            base = Path(anchor) / base
        kind = _peek_type(base)  # the type first: an idr folder has no weights of its own
        if kind is None or kind in SUPPORTED_BASE_TYPES or is_third_party_type(kind):
            try:
                kind = check_checkpoint_dir(base, "policy.base_policy_path")["type"]
            except ValueError as e:
                raise IDRConfigError(str(e)) from None
        if kind in REFUSED_BASE_TYPES:
            raise IDRConfigError(
                f"policy.base_policy_path={str(base)!r}: base type {kind!r} is refused: "
                f"{REFUSED_BASE_TYPES[kind]}. Supported: {', '.join(SUPPORTED_BASE_TYPES)}"
            )
        if kind not in SUPPORTED_BASE_TYPES and not is_third_party_type(kind):
            close = difflib.get_close_matches(
                str(kind), [*SUPPORTED_BASE_TYPES, *PreTrainedConfig.get_known_choices()], n=3
            )
            hint = f" (did you mean {', '.join(dict.fromkeys(close))}?)" if close else ""
            raise IDRConfigError(
                f"policy.base_policy_path={str(base)!r}: base type {kind!r}{hint} is not "
                f"supported by IDR: it is neither one of {', '.join(SUPPORTED_BASE_TYPES)} nor "
                "registered by an installed lerobot_policy_* plugin; fix the type in its "
                "config.json or install the plugin that registers it"
                + describe_failures(plugin_import_errors())
            )
        if self.base_weights_sha256:
            have = sha256_file(base / WEIGHTS)
            if have != self.base_weights_sha256:
                raise IDRConfigError(
                    f"policy.base_policy_path={str(base)!r}: its {WEIGHTS} changed since the IDR "
                    f"folder was made (sha256 {have[:12]}... != {self.base_weights_sha256[:12]}"
                    "...): remake the folder with lerobot-idr-wrap, or point base_policy_path at "
                    "the original weights"
                )
        self._check_method(base, kind)
        if "no_img" in passes(self.refiner()):  # the counterfactual passes intervene
            self._check_inputs(base)
        return base

    def _check_method(self, base: Path, kind: str) -> None:
        """The mode's method runs on this base (``idr_core.methods.refusal``, the rule of
        idr-eval's pre-flight): ``ensemble`` needs a base that samples, ``temporal`` a chunk of
        more than one executed action. Refused here, before any weight is loaded."""
        cfg = read_base_config(base)
        chunk = (
            self.n_action_steps
            or cfg.get("n_action_steps")
            or cfg.get("chunk_size")
            or cfg.get("action_chunk_size")  # VQ-BeT
        )
        why = refusal(
            self.refiner(),
            samples=kind not in DETERMINISTIC_TYPES,
            chunk_len=int(chunk) if chunk else None,
            hidden_objects=None,
            base=f"{base} (type {kind})",
            suite="",
        )
        if why is not None:
            raise IDRConfigError(f"policy.mode={self.mode!r}: {why}")

    def _check_inputs(self, base: Path) -> None:
        """The counterfactual passes need an image (do(V)) and a state (do(S)) in the base's
        inputs."""
        keys = list(read_base_config(base).get("input_features") or {})
        for missing, what in (
            (not any(is_image_key(k) for k in keys), "no image"),
            (OBS_STATE not in keys, f"no {OBS_STATE}"),
        ):
            if missing:
                raise IDRConfigError(
                    f"policy.base_policy_path={str(base)!r}: the base reads {what} (its inputs: "
                    f"{keys}), but policy.mode={self.mode!r} intervenes on the image and the "
                    "state; use --policy.mode=baseline, or a base that reads both"
                )

    # -- PreTrainedConfig's abstract members ----------------------------------------------
    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> None:
        return None

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self):
        raise IDRConfigError(
            "policy.type=idr is training-free: train the base policy (its own type), then wrap "
            "the checkpoint with lerobot-idr-wrap"
        )

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if not self.output_features or ACTION not in self.output_features:
            raise IDRConfigError(
                "the idr policy has no action output feature: its base config.json was not read "
                "(set policy.base_policy_path to a lerobot checkpoint folder)"
            )


class IDROverXVLAConfig(IDRConfig):
    """An ``idr`` config whose base is X-VLA.

    lerobot gives X-VLA its own env processors by ``isinstance(policy_cfg, XVLAConfig)``
    (``lerobot.envs.factory.make_env_pre_post_processors``), which an ``idr`` config would
    silently miss: the env's observations would reach X-VLA processed for another policy. This
    class is registered as a virtual subclass of ``XVLAConfig`` (``abc``), so that choice sees
    X-VLA; it is still type ``idr`` (not a registered choice of its own) and saves as one."""

    @property
    def type(self) -> str:
        return "idr"

    def _save_pretrained(self, save_directory: Path) -> None:
        self.__class__ = IDRConfig  # encoded as the registered idr config
        try:
            IDRConfig._save_pretrained(self, save_directory)
        finally:
            self.__class__ = IDROverXVLAConfig


def adopt_base_type(config: IDRConfig, base_type: str) -> None:
    """Make ``config`` look like its base where lerobot dispatches on the config's class."""
    if base_type == "xvla" and not isinstance(config, IDROverXVLAConfig):
        from lerobot.policies.xvla.configuration_xvla import XVLAConfig

        XVLAConfig.register(IDROverXVLAConfig)
        config.__class__ = IDROverXVLAConfig


def read_base_config(path: Path) -> dict:
    """The base checkpoint's config.json as a dict (read, not instantiated)."""
    try:
        cfg = json.loads((path / "config.json").read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise IDRConfigError(
            f"policy.base_policy_path={str(path)!r}: config.json cannot be read ({e}); give a "
            "lerobot checkpoint folder"
        ) from None
    if not isinstance(cfg, dict) or "type" not in cfg:
        raise IDRConfigError(
            f"policy.base_policy_path={str(path)!r}: config.json names no policy 'type'; "
            "give a lerobot checkpoint folder"
        )
    return cfg


@functools.cache
def _plugins_registered() -> bool:
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    return True


def is_third_party_type(kind: str) -> bool:
    """Whether ``kind`` is a policy type registered by an installed third-party plugin (a
    ``lerobot_policy_*`` distribution, imported here as lerobot's tools import it): IDR runs
    it on the generic path, through its own processors and predict_action_chunk."""
    if kind in SUPPORTED_BASE_TYPES or kind in REFUSED_BASE_TYPES:
        return False
    _plugins_registered()
    if kind not in PreTrainedConfig.get_known_choices():
        return False
    return not PreTrainedConfig.get_choice_class(kind).__module__.startswith("lerobot.")


def _peek_type(path: Path) -> str | None:
    try:
        cfg = json.loads((path / "config.json").read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError):
        return None
    return cfg.get("type") if isinstance(cfg, dict) else None


def _features(raw: dict) -> dict[str, PolicyFeature]:
    return {
        k: PolicyFeature(type=FeatureType(v["type"]), shape=tuple(v["shape"]))
        if isinstance(v, dict)
        else v
        for k, v in raw.items()
    }
