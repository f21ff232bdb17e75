"""The idr policy: a frozen base policy run on the factual inputs and two counterfactuals in one
batched forward (shared noise), diagnosed and refined per chunk (the paper's Method section).

The preprocessor (``processor_idr``) has already made the 3B rows ``[factual | do(V) | do(S)]``;
``predict_action_chunk`` runs the base once on them, keeps the executed horizon
(``n_action_steps``: the refiner's norms are over the chunk, so they are taken over the actions
that run), splits the thirds, unnormalizes them
(``refine_space=physical``), refines, applies the hardware safety rules and returns B chunks.
``select_action`` keeps its own queue of ``n_action_steps`` actions (the base's queue would be
fed 3B rows). Mode ``baseline`` hands ``select_action`` to the base unchanged.

The methods without counterfactual passes get the factual rows alone (no IDR step in the
preprocessor): ``ensemble`` runs the base on ``samples`` copies of them, each copy under its own
noise draw (the seeds ``idr_core.methods.sample_seeds`` derives from the step's, as idr-eval
draws them), and executes the mean; ``temporal`` infers at every ``select_action`` and executes
lerobot's ``ACTTemporalEnsembler``'s average of the overlapping chunks
(``runtime.TemporalEnsemble``, the harness's averager).

Safety on hardware: the refined action never leaves the base's action bounds (the dataset's
min/max where the stats hold them, widened to the base action itself so a gate that is off
changes nothing); a non-finite refinement, or an inference past ``deadline_ms``, executes the
base action for that chunk; each is counted in the sidecar.
"""

from __future__ import annotations

import time
from collections import deque
from pathlib import Path
from typing import Any

import torch
from idr_core.features import OBS_STATE, is_image_key
from idr_core.methods import combine, method_of, passes, sample_seeds
from idr_core.refiner import clip_into, refine
from idr_core.sampling import crn_mode, noise_shape
from idr_core.sidecar import SidecarWriter
from idr_core.three_pass import split3
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class
from lerobot.policies.pretrained import PreTrainedPolicy

from lerobot_policy_idr.configuration_idr import (
    IDRConfig,
    IDRConfigError,
    adopt_base_type,
    read_base_config,
)
from lerobot_policy_idr.processor_idr import BATCH_SIZE_KEY
from lerobot_policy_idr.runtime import (
    ACTION,
    TemporalEnsemble,
    action_bounds,
    base_input,
    history_length,
    step_noise,
)

#: batch entries that concatenate every row's image patches along dim 0 (Qwen-VL processors)
FLAT_PATCH_KEYS = ("pixel_values", "pixel_values_videos")
# one row per image (a batch row with several cameras has several), in batch-row order
PER_IMAGE_KEYS = ("image_grid_thw", "video_grid_thw")


class IDRPolicy(PreTrainedPolicy):
    """IDR around a lerobot policy (see the module docstring)."""

    config_class = IDRConfig
    name = "idr"

    def __init__(self, config: IDRConfig, **kwargs: Any) -> None:
        super().__init__(config)
        base_dir = config.resolve_base()
        base_cfg = PreTrainedConfig.from_pretrained(base_dir)
        base_cfg.device = config.device
        # as lerobot's CLIs set it: a type that builds a sub-model (EO1's VLM) builds it from
        # the saved config, not from its hub id, when it is loaded from a checkpoint
        base_cfg.pretrained_path = base_dir
        if not config.output_features:
            config.copy_features(read_base_config(base_dir))
        self.base_dir = base_dir
        self.base = get_policy_class(base_cfg.type).from_pretrained(base_dir, config=base_cfg)
        self.base.eval()
        self.refiner_cfg = config.refiner()
        self.crn = crn_mode(base_cfg.type, self.base.predict_action_chunk)
        if self.crn == "shared_noise" and noise_shape(base_cfg, 1, 1) is None:
            # a noise input of a shape not known here (a third-party type): fork the RNG
            self.crn = "seeded_rng"
        adopt_base_type(config, base_cfg.type)  # X-VLA: lerobot's env processors for X-VLA
        if config.mode != "baseline" and getattr(base_cfg, "temporal_ensemble_coeff", None):
            raise IDRConfigError(
                "the base ACT uses temporal ensembling (temporal_ensemble_coeff), which runs "
                "inside its own select_action: use mode=baseline, or a base without it"
            )
        self.action_dim = int(base_cfg.output_features[ACTION].shape[0])
        self.base_steps = int(
            getattr(base_cfg, "n_action_steps", None)
            or getattr(base_cfg, "chunk_size", None)
            or base_cfg.action_chunk_size  # VQ-BeT executes its whole chunk
        )
        self.n_action_steps = int(config.n_action_steps or self.base_steps)
        self.method = method_of(self.refiner_cfg)
        self.n_obs_steps = int(getattr(base_cfg, "n_obs_steps", 1) or 1)
        self._unnormalize, self._bounds = _action_unnormalizer(base_dir, config)
        self.sidecar = SidecarWriter(config.diagnostics_dir)
        self._episode = 0
        self._recorded = False
        self.reset()

    @classmethod
    def from_pretrained(
        cls, pretrained_name_or_path: str | Path, *, config: IDRConfig | None = None, **kwargs: Any
    ) -> IDRPolicy:
        """An IDR folder holds no weights of its own: the base is loaded from its path."""
        path = Path(pretrained_name_or_path)
        if config is None:
            config = PreTrainedConfig.from_pretrained(path)
        if not isinstance(config, IDRConfig):
            raise IDRConfigError(f"{path} is a {config.type!r} checkpoint, not an idr folder")
        if config.pretrained_path is None:
            config.pretrained_path = path
        policy = cls(config)
        policy.to(config.device)
        policy.eval()
        return policy

    # -- lerobot's policy interface ---------------------------------------------------------
    def get_optim_params(self) -> dict:
        return self.config.get_optimizer_preset()  # raises: training-free

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict | None]:
        self.config.get_optimizer_preset()  # raises: training-free
        raise AssertionError("unreachable")

    def reset(self) -> None:
        self.base.reset()
        self._queue: deque[torch.Tensor] = deque(maxlen=self.n_action_steps)
        self._frames: deque[dict[str, Any]] = deque(maxlen=history_length(self.base.config))
        self._fed: dict[str, deque[torch.Tensor]] | None = None  # queue-fed bases: IDR's queues
        self._ensembler: TemporalEnsemble | None = None  # mode temporal: this episode's averager
        self._steps = 0
        self._tick = 0
        if self._recorded:  # a new episode starts
            self._episode += 1
            self._recorded = False
            self.sidecar.flush()

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, torch.Tensor], **kwargs: Any) -> torch.Tensor:
        """B chunks of the mode's method. ``noise``: the base's noise (a ``seeded_rng`` base: a
        tensor of seeds); ``seed``: the step seed, as idr-eval passes it (a placebo's
        direction, an ensemble's draws, and the noise where none is given, drawn from it as
        idr-eval's backbone draws it); neither given: torch's RNG, as the base draws its own."""
        actions, rows = self._infer(batch, kwargs.get("noise"), kwargs.get("seed"))
        self.sidecar.add(rows)
        return actions

    @torch.no_grad()
    def select_action(self, batch: dict[str, torch.Tensor], **kwargs: Any) -> torch.Tensor:
        t0 = time.perf_counter()
        self._steps += 1
        if self.config.mode == "baseline":
            inferred = _queue_empty(self.base)
            action = self.base.select_action(batch, **kwargs)
            if inferred:  # the base predicted a chunk in this call: one sidecar row per env
                ms = (time.perf_counter() - t0) * 1e3
                self._record_baseline(action.shape[0], ms)
            return self._physical(action)
        if self.method.every_step:  # temporal ensembling: an inference at every step
            chunk, rows = self._infer(batch, kwargs.get("noise"), kwargs.get("seed"))
            if self._ensembler is None:  # the chunk length is the executed horizon's
                self._ensembler = TemporalEnsemble(self.refiner_cfg.te_coeff, chunk.shape[1])
            action = self._ensembler.update(chunk)
            wait = (time.perf_counter() - t0) * 1e3
            self.sidecar.add([{**r, "wait_ms": wait} for r in rows])
            return action
        if not self._queue:
            chunk, rows = self._infer(batch, kwargs.get("noise"), kwargs.get("seed"))
            self._queue.extend(chunk[:, : self.n_action_steps].transpose(0, 1))
            wait = (time.perf_counter() - t0) * 1e3
            self.sidecar.add([{**r, "wait_ms": wait} for r in rows])
        else:  # no inference: the frame still joins the history, as the base's own queues take
            self._with_history(self._own_rows(batch))  # every step's frame (Diffusion, VQ-BeT)
        return self._queue.popleft()

    # -- the three passes, the diagnosis and the refinement ---------------------------------
    def _infer(
        self, batch: dict[str, Any], noise: Any = None, seed: int | None = None
    ) -> tuple[torch.Tensor, list[dict]]:
        """``seed``: the step seed (see ``predict_action_chunk``); None draws what it gives
        from torch's RNG, as the base's own noise is drawn."""
        t0 = time.perf_counter()
        if "no_img" not in self.method.passes:  # baseline, ensemble, temporal: factual rows
            return self._infer_factual(batch, noise, seed, t0)
        rows_in = _batch_rows(batch)
        b = int(batch.get(BATCH_SIZE_KEY, rows_in // 3))
        if rows_in != 3 * b:
            raise ValueError(
                f"the idr policy got {rows_in} rows, not 3 x {b}: its preprocessor must hold "
                "the idr_counterfactual_batch step (load it with the idr folder's processors)"
            )
        batch = self._with_history(batch)
        # the thirds the method reads, in one forward: all three, or cfg's factual and do(V)
        # (the rows idr-eval's runtime forwards, so the forward's shape, and with it the
        # float order on a CPU whose kernels depend on the batch, is the harness's)
        k = len(self.method.passes)
        version = weights_version(self.base)
        if noise is None and seed is not None:  # the noise idr-eval draws from the step seed
            noise = self._noise(b, seed)
        if noise is None and self.crn == "shared_noise":
            shape = noise_shape(self.base.config, b, self.action_dim)
            if shape is not None:  # one draw from torch's RNG, shared by the thirds
                noise = torch.randn(shape, device=_batch_device(batch))
        if self.crn == "seeded_rng":  # X-VLA ignores a noise input: a forward a third, one seed
            out = self._seeded_thirds(batch, b, noise, k)
        else:
            read = {key: _rows_of(v, 0, b, key, count=k) for key, v in batch.items()}
            if noise is None:
                out = self._predict(read)
            else:  # one draw, shared by the thirds read
                out = self._predict(read, noise=torch.cat([noise] * k))
        if weights_version(self.base) != version:
            raise IDRConfigError(
                f"the base policy (type {self.base.config.type!r}) changed its own weights during "
                "predict_action_chunk (test-time training?): IDR's three passes must run one "
                "network, and its counterfactual rows would train it. Run it with "
                "--policy.mode=baseline, or turn the base's adaptation off"
            )
        forward_ms = (time.perf_counter() - t0) * 1e3
        t1 = time.perf_counter()
        # the executed horizon: E_img is a norm over the chunk, so it is taken over the actions
        # that will run (n_action_steps), as idr-eval does
        out = out[:, : self.n_action_steps]
        if k == 3:
            a_base, a_no_img, a_no_prop = split3(self._physical(out), b)
        else:  # cfg: no do(S) third
            physical = self._physical(out)
            a_base, a_no_img, a_no_prop = physical[:b], physical[b : 2 * b], None
        if seed is None and self.config.mode in ("random", "shuffled"):
            seed = _draw()
        final, diag, clipped, fallback = self._refine(a_base, a_no_img, a_no_prop, seed or 0)
        now = time.perf_counter()
        total = (now - t0) * 1e3
        if self.refiner_cfg.refines and self.config.deadline_ms and total > self.config.deadline_ms:
            final, fallback = a_base, ["deadline"] * b
        rows = self._rows(
            b,
            diag,
            forward_ms=forward_ms,
            refine_ms=(now - t1) * 1e3,
            inference_ms=total,
            clipped=clipped,
            fallback=fallback,
            pass_rows=k,
            executed_steps=self.n_action_steps,
        )
        return final, rows

    def _infer_factual(
        self, batch: dict[str, Any], noise: Any, seed: int | None, t0: float
    ) -> tuple[torch.Tensor, list[dict]]:
        """A method of factual passes alone (``passes``: baseline and temporal one, ensemble
        ``samples``), on the batch's factual rows, combined by ``idr_core.methods.combine``."""
        names = passes(self.refiner_cfg)
        batch = self._with_history(self._own_rows(batch))
        b = _batch_rows(batch)
        k = len(names)
        if k > 1 and seed is None:  # the step's draws: from torch's RNG, as its noise is
            seed = int(noise[0]) if self.crn == "seeded_rng" and noise is not None else _draw()
        if noise is None and seed is not None:
            noise = self._noise(b, seed)
        if k == 1:
            out = self._forward(batch, noise)
        else:
            version = weights_version(self.base)
            out = self._draws(batch, b, noise, sample_seeds(seed, k))
            if weights_version(self.base) != version:
                raise IDRConfigError(
                    f"the base policy (type {self.base.config.type!r}) changed its own weights "
                    f"during predict_action_chunk: mode {self.config.mode!r} runs it {k} times "
                    "on one observation and must run one network. Run it with "
                    "--policy.mode=baseline, or turn the base's adaptation off"
                )
        forward_ms = (time.perf_counter() - t0) * 1e3
        t1 = time.perf_counter()
        out = self._physical(out[:, : self.n_action_steps])
        parts = [out[i * b : (i + 1) * b] for i in range(k)]
        final, _ = combine(self.refiner_cfg, parts)
        clipped, fallback = [0] * b, [""] * b
        if k > 1:  # the ensemble's mean: the safety rules of a refined chunk
            final, clipped, fallback = self._safe(final, parts[0])
        now = time.perf_counter()
        rows = self._rows(
            b,
            None,
            forward_ms=forward_ms,
            refine_ms=(now - t1) * 1e3,
            inference_ms=(now - t0) * 1e3,
            clipped=clipped,
            fallback=fallback,
            pass_rows=k,
            executed_steps=1 if self.method.every_step else self.n_action_steps,
        )
        return final, rows

    def _own_rows(self, batch: dict[str, Any]) -> dict[str, Any]:
        """The rows the mode's method reads: all (three-pass modes), else the factual ones."""
        return batch if "no_img" in self.method.passes else _factual_rows(batch)

    def _noise(self, b: int, seed: int) -> Any:
        """The noise idr-eval's backbone draws from ``seed`` for ``b`` rows (None: the base
        takes none)."""
        return step_noise(self.base.config, self.crn, b, self.action_dim, seed, self.config.device)

    def _forward(self, batch: dict[str, Any], noise: Any) -> torch.Tensor:
        """One forward of the factual rows under ``noise`` (a seeded base: under its seed;
        None: the base draws its own)."""
        if noise is None or self.crn == "deterministic":
            return self._predict(batch)
        if self.crn == "seeded_rng":
            return self._seeded(batch, int(noise[0]))
        return self._predict(batch, noise=noise)

    def _draws(self, batch: dict[str, Any], b: int, noise: Any, seeds: list[int]) -> torch.Tensor:
        """``len(seeds)`` draws for the factual rows, in order, as idr-eval's harness runs an
        ensemble's passes: a shared-noise base in one forward of the rows repeated, each copy
        with its seed's noise (the first ``noise`` where given); a seeded base in one forward
        per seed."""
        if self.crn == "seeded_rng":
            return torch.cat([self._seeded(batch, s) for s in seeds], dim=0)
        noises = [noise if noise is not None else self._noise(b, seeds[0])]
        noises += [self._noise(b, s) for s in seeds[1:]]
        return self._predict(_repeat_rows(batch, len(seeds), b), noise=torch.cat(noises, dim=0))

    def _seeded(self, part: dict[str, Any], seed: int, rows: slice | None = None) -> torch.Tensor:
        """The base's forward on ``part`` under a forked torch RNG seeded with ``seed``."""
        device = _batch_device(part)
        with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
            torch.manual_seed(seed)
            return self._predict(part, rows)

    def _seeded_thirds(
        self, batch: dict[str, Any], b: int, seed: Any, thirds: int = 3
    ) -> torch.Tensor:
        """The ``thirds`` thirds as forwards of B rows each, each under a forked RNG seeded alike
        (``seed``: a tensor of seeds as idr-eval's backbone makes it, else one draw from torch's
        RNG), so the thirds see the same sampling noise."""
        s = int(seed[0]) if seed is not None else _draw()
        outs = []
        for i in range(thirds):
            part = {k: _rows_of(v, i, b, k) for k, v in batch.items()}
            outs.append(self._seeded(part, s, slice(i * b, (i + 1) * b)))
        return torch.cat(outs, dim=0)

    def _safe(
        self, final: torch.Tensor, a_base: torch.Tensor
    ) -> tuple[torch.Tensor, list[int], list[str]]:
        """A refined chunk under the hardware rules: a non-finite one executes ``a_base``; it is
        clipped into the base's action bounds (widened to ``a_base``) where it has them."""
        b = a_base.shape[0]
        if not bool(torch.isfinite(a_base).all()):
            raise ValueError("the base policy's action is not finite; nothing safe to execute")
        if not bool(torch.isfinite(final).all()):
            return a_base, [0] * b, ["nonfinite"] * b
        clipped = [0] * b
        if self._bounds is not None and self.refiner_cfg.clip_actions:
            final, clipped = clip_into(final, a_base, *self._bounds)
        return final, clipped, [""] * b

    def _refine(
        self,
        a_base: torch.Tensor,
        a_no_img: torch.Tensor,
        a_no_prop: torch.Tensor | None,
        seed: int,
    ):
        b = a_base.shape[0]
        if not bool(torch.isfinite(a_base).all()):
            raise ValueError("the base policy's action is not finite; nothing safe to execute")
        counterfactual = [a for a in (a_no_img, a_no_prop) if a is not None]
        if not all(bool(torch.isfinite(a).all()) for a in counterfactual):
            return a_base, None, [0] * b, ["nonfinite"] * b
        if method_of(self.refiner_cfg).diagnoses:
            final, diag = refine(a_base, a_no_img, a_no_prop, self.refiner_cfg, seed=seed)
        else:  # cfg: the factual and do(V) thirds (the do(S) third is not read)
            final, diag = combine(self.refiner_cfg, [a_base, a_no_img])
        if not self.refiner_cfg.refines:
            return final, diag, [0] * b, [""] * b
        final, clipped, fallback = self._safe(final, a_base)
        return final, diag, clipped, fallback

    def _physical(self, actions: torch.Tensor) -> torch.Tensor:
        return actions if self._unnormalize is None else self._unnormalize(actions)

    def _predict(self, batch: dict[str, Any], rows: slice | None = None, **kw: Any) -> torch.Tensor:
        """The base's ``predict_action_chunk``; a queue-fed base reads IDR's queues (``rows``
        of them: one third in a seeded pass), lent for the call, its own restored after."""
        if self._fed is None:
            return self.base.predict_action_chunk(batch, **kw)
        own = self.base._queues
        self.base._queues = {
            k: deque((x if rows is None else x[rows] for x in q), maxlen=q.maxlen)
            for k, q in self._fed.items()
        }
        try:
            return self.base.predict_action_chunk(batch, **kw)
        finally:
            self.base._queues = own

    def _with_history(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Observation history where the base reads one: the frame joins the episode's last
        ``history_length`` frames of the 3B rows, and ``runtime.base_input`` (the code
        idr-eval's harness runs too) builds what the base reads from them: Diffusion's stacked
        frames (the first repeated at an episode's start, as its own select_action does), a
        queue-fed base's (VQ-BeT) queues filled by lerobot's ``populate_queues``."""
        self._frames.append(batch)
        out, self._fed = base_input(
            self.base.config, getattr(self.base, "_queues", None), list(self._frames)
        )
        return out

    # -- the sidecar ----------------------------------------------------------------------
    def _rows(self, b: int, diag: Any, **columns: Any) -> list[dict[str, Any]]:
        d = diag.to_numpy() if diag is not None else {}
        now = time.time()
        rows = []
        for i in range(b):
            row = {
                "episode": self._episode,
                "tick": self._tick,
                "env": i,
                "step": self._steps,
                "wall_time": now,
                "mode": self.config.mode,
                **{k: (v[i] if isinstance(v, list) else v) for k, v in columns.items()},
            }
            for k, v in d.items():
                row[k] = float(v[i])
            rows.append(row)
        self._tick += 1
        self._recorded = True
        return rows

    def _record_baseline(self, b: int, ms: float) -> None:
        self.sidecar.add(
            self._rows(
                b,
                None,
                forward_ms=ms,
                inference_ms=ms,
                wait_ms=ms,
                pass_rows=1,
                executed_steps=self.base_steps,  # the base's select_action runs its own queue
            )
        )


def _batch_rows(batch: dict[str, Any]) -> int:
    for key, value in batch.items():
        if isinstance(value, torch.Tensor) and (key == OBS_STATE or is_image_key(key)):
            return int(value.shape[0])
    raise ValueError(f"the idr policy found no state or image tensor in the batch: {sorted(batch)}")


def _rows_of(value: Any, i: int, b: int, key: str = "", count: int = 1) -> Any:
    """Thirds ``i`` to ``i + count - 1`` of a 3B-row batch entry (tensors and per-row lists;
    others as they are). A Qwen-VL processor's ``pixel_values`` hold every row's image patches
    one after another (EO1): the thirds are its thirds, the three thirds' images being of one
    size; its ``image_grid_thw`` has one row per image, so several per batch row with several
    cameras."""
    j = i + count
    if isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == 3 * b:
        return value[i * b : j * b]
    if key in FLAT_PATCH_KEYS and isinstance(value, torch.Tensor) and value.shape[0] % 3 == 0:
        n = value.shape[0] // 3
        return value[i * n : j * n]
    if key in PER_IMAGE_KEYS and isinstance(value, torch.Tensor) and value.shape[0] % (3 * b) == 0:
        n = value.shape[0] // 3  # one row per image, several cameras per batch row
        return value[i * n : j * n]
    if isinstance(value, list) and len(value) == 3 * b:
        return value[i * b : j * b]
    return value


def _factual_rows(batch: dict[str, Any]) -> dict[str, Any]:
    """The factual rows of a batch: all of it, or its first third where a preprocessor with
    IDR's counterfactual step (a folder made for a three-pass mode) tripled it."""
    if BATCH_SIZE_KEY not in batch:
        return batch
    b = int(batch[BATCH_SIZE_KEY])
    out = {k: _rows_of(v, 0, b, k) for k, v in batch.items()}
    out.pop(BATCH_SIZE_KEY)
    return out


def _repeat_rows(batch: dict[str, Any], k: int, b: int) -> dict[str, Any]:
    """The batch's ``b`` rows ``k`` times over, in order (tensors and per-row lists)."""
    out = {}
    for key, value in batch.items():
        if isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == b:
            value = torch.cat([value] * k, dim=0)
        elif isinstance(value, list) and len(value) == b:
            value = value * k
        out[key] = value
    return out


def _draw() -> int:
    """A seed from torch's global RNG (where lerobot's tools take a base's noise from)."""
    return int(torch.randint(0, 2**31 - 1, ()))


def _batch_device(batch: dict[str, Any]) -> torch.device:
    for value in batch.values():
        if isinstance(value, torch.Tensor):
            return value.device
    return torch.device("cpu")


def _queue_empty(policy: PreTrainedPolicy) -> bool:
    """Whether the policy's next select_action predicts a new chunk (its action queue is
    empty): ``_action_queue`` (act, pi0, pi05, tiny_vla) or ``_queues['action']`` (diffusion,
    smolvla)."""
    q = getattr(policy, "_action_queue", None)
    if q is None:
        q = getattr(policy, "_queues", {}).get(ACTION)
    return q is None or len(q) == 0


def weights_version(module: torch.nn.Module) -> int:
    """The sum of the parameters' version counters: torch bumps a tensor's counter at every
    in-place write (an optimizer step, a copy_), inference mode included."""
    return sum(p._version for p in module.parameters())


def _action_unnormalizer(base_dir: Path, config: IDRConfig):
    """The base's postprocessor up to its action unnormalizer, as a callable on action tensors,
    and the action bounds the unnormalizer knows (dataset min/max), for
    ``refine_space=physical``; (None, None) otherwise."""
    if config.refine_space != "physical":
        return None, None
    from lerobot.processor import PolicyProcessorPipeline
    from lerobot.processor.converters import (
        policy_action_to_transition,
        transition_to_policy_action,
    )

    post = PolicyProcessorPipeline.from_pretrained(
        str(base_dir),
        config_filename="policy_postprocessor.json",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )
    names = [type(s).__name__ for s in post.steps]
    if "UnnormalizerProcessorStep" not in names:
        return None, None
    # the unnormalizer and the steps before it, which act in the normalized space (VLA-JEPA
    # clips its actions and snaps its gripper there): the policy's physical actions are the
    # base's, and the folder's postprocessor keeps the steps after (processor_idr)
    before = post.steps[: names.index("UnnormalizerProcessorStep") + 1]
    step = before[-1]
    for s in before:
        if hasattr(s, "to"):
            s.to(device=config.device)
    unnormalize = PolicyProcessorPipeline(
        steps=before,
        name="idr_action_unnormalizer",
        to_transition=policy_action_to_transition,
        to_output=transition_to_policy_action,
    )
    return unnormalize, action_bounds([step])
