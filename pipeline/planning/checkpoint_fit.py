"""Pre-flight: does the checkpoint fit the env? Checked on the driver before any actor starts.

The env says what it renders and accepts (``describe``: cameras, image size, state and action
dims, its protocol); the checkpoint what it reads (its config.json). :func:`fit_backbone_to_env`
matches the two and returns what the run then uses: which env camera feeds which image key
(by the names checkpoints give robosuite's cameras, unless ``backbone.params.camera_map`` says),
the render size (the checkpoint's, where the env's protocol leaves it to the checkpoint) and the
actions executed per inference. A mismatch is one ConfigError naming both sides and the fix.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from idr_core.features import IMAGE_PREFIX, OBS_STATE

from pipeline.planning.config import DEFAULT_REPLAN_STEPS, ConfigError, RunConfig
from workers.io_spec import EnvIO, PolicyIO, Replan


@dataclass(frozen=True)
class Fit:
    """What the pre-flight settled, applied to the config the run uses (and logged)."""

    replan_steps: Replan
    camera_map: dict[str, str] | None = None  # env camera -> image key suffix; None: not ours
    image_size: int | None = None  # set on env.params when the checkpoint decided it
    protocol: Mapping[str, object] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    # do(S) under state_space=centered: {"values": the dataset mean state or None (zero),
    # "source": where it was read}; None: no cell takes do(S) centered
    state_center: Mapping[str, Any] | None = None

    def record(self) -> dict[str, Any]:
        out: dict[str, Any] = {"replan_steps": self.replan_steps}
        if self.state_center is not None:
            out["do_state_center"] = dict(self.state_center)
        if self.camera_map is not None:
            out["camera_map"] = self.camera_map
        if self.image_size is not None:
            out["image_size"] = self.image_size
        if self.notes:
            out["notes"] = list(self.notes)
        return out


def _env_side(env: EnvIO) -> str:
    sizes = {env.size_label(c) for c in env.cameras}
    if len(sizes) == 1:
        return f"the env renders {list(env.cameras)} at {sizes.pop()} px"
    return f"the env renders { ({c: env.size_label(c) for c in env.cameras}) } px"


def match_cameras(
    env: EnvIO, policy: PolicyIO, camera_map: Mapping[str, str] | None
) -> dict[str, str]:
    """env camera -> image key suffix, covering every image key the checkpoint declares."""
    keys = sorted(policy.images)
    if camera_map is not None:
        unknown = [c for c in camera_map if c not in env.cameras]
        if unknown:
            raise ConfigError(
                f"backbone.params.camera_map names env cameras {unknown} that the env does not "
                f"render; env cameras: {list(env.cameras)} (env.params.cameras)"
            )
        given = sorted(camera_map.values())
        if given != keys:
            raise ConfigError(
                f"backbone.params.camera_map={dict(camera_map)} feeds image keys "
                f"{[IMAGE_PREFIX + k for k in given]}, but {policy.source} declares "
                f"{[IMAGE_PREFIX + k for k in keys]}: map one env camera to each"
            )
        return dict(camera_map)
    mapping: dict[str, str] = {}
    for key in keys:
        cams = [c for c in env.cameras if key == c or key in env.camera_aliases.get(c, ())]
        if len(cams) != 1:
            known = {c: [c, *env.camera_aliases.get(c, ())] for c in env.cameras}
            why = "matches no env camera" if not cams else f"matches several env cameras {cams}"
            raise ConfigError(
                f"{policy.source} reads {IMAGE_PREFIX + key}, which {why}; {_env_side(env)} "
                f"known by the names {known}. Set backbone.params.camera_map={{<env camera>: "
                f"{key}, ...}} for every image key, or render the camera it needs "
                "(env.params.cameras)"
            )
        if cams[0] in mapping:
            raise ConfigError(
                f"{policy.source} reads {IMAGE_PREFIX + mapping[cams[0]]} and "
                f"{IMAGE_PREFIX + key}, both names of env camera {cams[0]!r}: set "
                "backbone.params.camera_map"
            )
        mapping[cams[0]] = key
    return mapping


def _image_size(env: EnvIO, policy: PolicyIO, mapping: Mapping[str, str]) -> int | None:
    """The render size the checkpoint sets (None: the env's stands); refuse sizes that do not
    fit a policy that does not resize its images."""
    shapes = {key: policy.images[key] for key in mapping.values()}
    sizes = {(s[1], s[2]) for s in shapes.values()}
    declared = ", ".join(f"{IMAGE_PREFIX}{k} {tuple(s)}" for k, s in sorted(shapes.items()))
    bad_channels = [k for k, s in shapes.items() if s[0] != 3]
    if bad_channels:
        raise ConfigError(
            f"{policy.source} declares {declared}: the env renders RGB (3 channels); a "
            "checkpoint trained on other images cannot run here"
        )
    if env.image_size_from_checkpoint and sizes:
        if len(sizes) == 1 and (h_w := sizes.pop())[0] == h_w[1]:
            return h_w[0]
        raise ConfigError(
            f"{policy.source} declares {declared}: not one square size the env can render for "
            "all cameras; set env.params.image_size (the policy must then resize)"
        )
    wrong = {
        key: shape
        for cam, key in mapping.items()
        if ((shape := policy.images[key])[1], shape[2]) != env.hw_of(cam)
    }
    if wrong and not policy.resizes_images:
        h = next(iter(wrong.values()))[1]
        if env.camera_sizes:  # sizes fixed per camera by the benchmark: nothing to set
            rendered = ", ".join(f"{c!r} at {env.size_label(c)}" for c in mapping)
            raise ConfigError(
                f"image size: the env renders {rendered} px (fixed by the env), but "
                f"{policy.source} declares {declared} and does not resize its inputs"
            )
        raise ConfigError(
            f"image size: {_env_side(env)}, but {policy.source} declares {declared} and does "
            f"not resize its inputs; set env.params.image_size={h} (lerobot-eval: "
            f"--env.observation_height={h} --env.observation_width={h})"
        )
    return None


def resolve_replan(requested: Replan | None, env: EnvIO | None, policy: PolicyIO | None) -> Replan:
    """Actions executed per inference: as configured, else the env protocol's rule, else the
    n_action_steps of a checkpoint trained on data (what the idr policy executes in lerobot's
    tools), else 4; ``chunk`` is the checkpoint's n_action_steps where it declares one."""
    rule = requested if requested is not None else (env.replan if env else None)
    if rule is None:
        if policy is not None and policy.trained_on_data:
            return policy.chunk_len
        return DEFAULT_REPLAN_STEPS
    if rule == "chunk" and policy is not None:
        return policy.chunk_len
    return rule


def fit_backbone_to_env(
    env: EnvIO | None,
    policy: PolicyIO | None,
    requested_replan: Replan | None,
    camera_map: Mapping[str, str] | None,
) -> Fit:
    """Match what the checkpoint reads with what the env gives; ConfigError on a mismatch."""
    replan = resolve_replan(requested_replan, env, policy)
    protocol = dict(env.protocol) if env else {}
    if protocol:
        protocol["replan"] = replan
    if env is None or policy is None:
        return Fit(replan, protocol=protocol)
    mapping = match_cameras(env, policy, camera_map)
    if policy.state_dim is not None and policy.state_dim != env.state_dim:
        raise ConfigError(
            f"state: the env gives a {env.state_dim}-d state, but {policy.source} declares "
            f"{OBS_STATE} ({policy.state_dim},); use a checkpoint trained on this env's "
            "state layout (docs/suites/index.md: what each suite gives a policy)"
        )
    if policy.action_dim != env.action_dim:
        raise ConfigError(
            f"action: the env takes {env.action_dim}-d actions, but {policy.source} declares "
            f"action ({policy.action_dim},); use a checkpoint trained on this env's action space"
        )
    size = _image_size(env, policy, mapping)
    notes = []
    if size is not None:
        notes.append(f"image_size {size} px from the checkpoint (protocol {protocol.get('name')})")
    if camera_map is None and any(k != v for k, v in mapping.items()):
        notes.append(f"camera_map {mapping} by the checkpoint's camera names")
    if protocol and size is not None:  # the size the protocol left to the checkpoint
        protocol["image_size"] = size
    return Fit(replan, mapping or None, size, protocol, tuple(notes))


def describe_env(suite: str, params: dict[str, Any]) -> EnvIO | None:
    from workers.envs.base import suite_hooks
    from workers.envs.factory import env_class

    describe = suite_hooks(env_class(suite)).describe
    return None if describe is None else describe(**params)


def describe_backbone(kind: str, params: dict[str, Any]) -> PolicyIO | None:
    from workers.backbones.base import backbone_member
    from workers.backbones.factory import backbone_class

    describe = backbone_member(backbone_class(kind), "describe")
    return None if describe is None else describe(params)


def _check_intervention_spaces(cfg: RunConfig) -> None:
    """The wrapper's own check (normalized-space interventions only where the backbone applies
    them), for every cell, here before any actor rather than as an error row per episode."""
    from workers.backbones.factory import backbone_class
    from workers.policy.wrapper import check_intervention_spaces

    cls = backbone_class(cfg.backbone.kind)
    try:
        for cell in cfg.cells():
            check_intervention_spaces(cls, cfg.backbone.kind, cell.intervention)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def check_inputs_for_modes(
    cfg: RunConfig, policy: PolicyIO | None, env: EnvIO | None = None
) -> None:
    """A cell that runs the counterfactual passes (IDR's modes, ``diagnose``, its controls,
    ``cfg``) needs an env that renders an image and a checkpoint that reads an image (do(V))
    and a state (do(S))."""
    from idr_core.methods import passes

    modes = sorted({c.idr.mode for c in cfg.cells() if {"no_img", "no_prop"} & set(passes(c.idr))})
    if not modes:
        return
    needs = f"grid: mode {', '.join(modes)} intervenes on the image and the state"
    if env is not None and not env.cameras:
        fix = f"set {env.image_option}, or " if env.image_option else ""
        raise ConfigError(
            f"{needs}, but env.suite={cfg.env.suite!r} with these params renders no camera; "
            f"{fix}run it with mode baseline only"
        )
    if policy is None or not policy.declares_inputs:
        return
    for missing, what in ((not policy.images, "no image"), (policy.state_dim is None, "no state")):
        if missing:
            raise ConfigError(
                f"{needs}, but {policy.source} reads {what}; run this checkpoint with mode "
                "baseline only, or use a checkpoint that reads both"
            )


def state_center(cfg: RunConfig, policy: PolicyIO | None) -> dict[str, Any] | None:
    """What do(S) is taken about in the run's ``centered`` cells (the base's dataset mean
    state, or zero for a base without dataset statistics), recorded with the run; refused for
    a checkpoint trained on data whose files hold no state mean. None: no such cell."""
    from idr_core.methods import passes

    centered = [
        c.cell_id
        for c in cfg.cells()
        if c.intervention.state_space == "centered" and "no_prop" in passes(c.idr)
    ]
    if not centered:
        return None
    if policy is None or policy.state_dim is None or not policy.trained_on_data:
        return {"values": None, "source": f"zero: backbone {cfg.backbone.kind!r} declares no "
                "dataset statistics"}  # fmt: skip
    if policy.state_mean is None:
        raise ConfigError(
            f"intervention.state_space=centered (cells {', '.join(centered)}): {policy.source} "
            "holds no dataset mean of observation.state in its preprocessor's normalizer; set "
            "intervention.state_space to raw or normalized"
        )
    if len(policy.state_mean) != policy.state_dim:
        raise ConfigError(
            f"intervention.state_space=centered: {policy.state_mean_source} holds a state mean "
            f"of {len(policy.state_mean)} values, the checkpoint reads {policy.state_dim}"
        )
    return {"values": list(policy.state_mean), "source": policy.state_mean_source}


def check_methods(cfg: RunConfig, policy: PolicyIO | None) -> None:
    """Every cell's test-time method runs on this base and suite (``idr_core.methods``): an
    ensemble needs a base that samples, temporal ensembling a base with chunks, the
    object-hidden contrast a suite that renders it. Refused here, before any episode."""
    from idr_core.methods import refusal

    from workers.envs.base import suite_info
    from workers.envs.factory import env_class

    hidden = getattr(suite_info(env_class(cfg.env.suite)), "renders_hidden_objects", None)
    for cell in cfg.cells():
        why = refusal(
            cell.idr,
            samples=None if policy is None else policy.samples,
            chunk_len=None if policy is None else policy.chunk_len,
            hidden_objects=hidden,
            base=policy.source if policy is not None else cfg.backbone.kind,
            suite=cfg.env.suite,
        )
        if why is not None:
            raise ConfigError(f"grid: cell {cell.cell_id!r}: {why}")


def lerobot_eval_threads() -> int:
    """The torch thread count lerobot-eval runs with here: torch's default, the CPUs this
    process may use unless OMP_NUM_THREADS says otherwise."""
    import os

    env = os.environ.get("OMP_NUM_THREADS", "")
    if env.isdigit() and int(env) > 0:
        return int(env)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def with_thread_note(fit: Fit, cfg: RunConfig) -> Fit:
    """Under lerobot-eval's protocol, the torch thread count the run uses, in the protocol record
    and in a pre-flight line: a float reduction splits by thread, so an episode equals
    lerobot-eval's bit for bit only with equal threads (lerobot-eval runs torch's default)."""
    if fit.protocol.get("name") != "lerobot" or cfg.backbone.kind == "remote":
        return fit
    threads, theirs = cfg.executor.threads(), lerobot_eval_threads()
    if threads == theirs:
        note = f"torch threads {threads}, as lerobot-eval runs here: its episodes bit for bit"
    else:
        note = (
            f"torch threads {threads} per actor, lerobot-eval runs {theirs} here: episodes equal "
            f"lerobot-eval's in protocol, not bit for bit (executor.torch_threads={theirs} for "
            "that)"
        )
    protocol = {**fit.protocol, "torch_threads": threads}
    return replace(fit, protocol=protocol, notes=(*fit.notes, note))


def fit_config(cfg: RunConfig) -> tuple[RunConfig, Fit]:
    """The config with what the pre-flight settled filled in (replan steps; camera map and
    image size where the checkpoint decides them), and the fit itself."""
    try:
        env = describe_env(cfg.env.suite, cfg.env.params)
        policy = describe_backbone(cfg.backbone.kind, cfg.backbone.params)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    camera_map = cfg.backbone.params.get("camera_map")
    if camera_map is not None and not isinstance(camera_map, dict):
        raise ConfigError(
            f"backbone.params.camera_map must map env camera -> image key, got {camera_map!r}"
        )
    _check_intervention_spaces(cfg)
    check_inputs_for_modes(cfg, policy, env)
    check_methods(cfg, policy)
    if env is None and policy is not None:  # an env without describe: its class's action dim
        from workers.envs.base import suite_info
        from workers.envs.factory import env_class

        dim = suite_info(env_class(cfg.env.suite)).action_dim
        if isinstance(dim, int) and dim != policy.action_dim:
            raise ConfigError(
                f"action: the env takes {dim}-d actions, but {policy.source} declares action "
                f"({policy.action_dim},); use a policy trained on this env's action space"
            )
    center = state_center(cfg, policy)
    fit = with_thread_note(
        fit_backbone_to_env(env, policy, cfg.backbone.replan_steps, camera_map), cfg
    )
    fit = replace(fit, state_center=center)
    if env is not None:  # a served model: one trial answer on an observation shaped like the env's
        from workers.backbones.base import backbone_member
        from workers.backbones.factory import backbone_class

        dry_run = backbone_member(backbone_class(cfg.backbone.kind), "dry_run")
        if dry_run is not None:
            try:
                dry_run(dict(cfg.backbone.params), env)
            except ValueError as e:
                raise ConfigError(str(e)) from None
    backbone = dict(cfg.backbone.params)
    if fit.camera_map is not None and any(k != v for k, v in fit.camera_map.items()):
        backbone["camera_map"] = fit.camera_map  # same names need none (the adapter's default)
    env_params = dict(cfg.env.params)
    if fit.image_size is not None:
        env_params["image_size"] = fit.image_size
    resolved = cfg.model_copy(
        update={
            "backbone": cfg.backbone.model_copy(
                update={"params": backbone, "replan_steps": fit.replan_steps}
            ),
            "env": cfg.env.model_copy(update={"params": env_params}),
        }
    )
    return resolved, fit
