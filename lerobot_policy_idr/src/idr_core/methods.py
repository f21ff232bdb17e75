"""The test-time methods, IDR among them: which forwards each needs, which settings it reads,
what it asks of the base and the env, and how its forwards become the executed chunk.

One table, read by the harness (planning refuses a cell a base or suite cannot run, the
wrapper builds the passes, the actor executes) and by the lerobot policy type ``idr``. Every
method is a value of the ``mode`` axis, so a grid sets methods side by side with IDR's own
modes and every effect has its control in the same grid:

- IDR and its ablations (``E``, ``A``-``D``, ``F``), the diagnosis alone (``diagnose``) and the
  base alone (``baseline``);
- E's controls, which keep its three passes and gate (``random``, ``shuffled``, ``scale_free``,
  in ``idr_core.refiner``);
- image guidance classifier-free style (``cfg``): factual and do(V) passes;
- sample ensembling (``ensemble``): ``samples`` factual passes with independent noise;
- temporal ensembling (``temporal``): one factual pass at every env step, averaged over the
  overlapping chunks by lerobot's ``ACTTemporalEnsembler`` in the execution loop;
- Policy Contrastive Decoding's contrast (``pcd``): factual and objects-hidden passes.

Passes are named: ``factual``, ``no_img`` (do(V)), ``no_prop`` (do(S)), ``no_objects`` (the
task's objects hidden at render time) and ``sample`` (the factual input under another noise
draw). A pass that is not ``sample`` shares the factual pass's noise (common random numbers).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from idr_core.refiner import MODE_DESCRIPTIONS, MODES, REFINER_MODES, RefinerConfig, refine

#: settings of ``RefinerConfig`` that choose a method's behaviour (``mode`` itself aside)
SETTINGS = ("alpha", "beta", "lam", "tau", "eps", "guidance", "w", "samples", "te_coeff", "horizon")
_IDR_READS = frozenset({"alpha", "beta", "lam", "tau", "eps", "guidance", "horizon"})
#: what each of E's ablations leaves unused: D has no gate, A no stabilizer, B no clip
_UNUSED_BY_ABLATION = {"D": {"tau"}, "A": {"beta", "lam"}, "B": {"lam"}}


@dataclass(frozen=True)
class Method:
    """One test-time method (a value of ``mode``)."""

    name: str
    passes: tuple[str, ...]  # the forwards of one inference, factual first
    reads: frozenset[str]  # the settings it reads (SETTINGS)
    sampling: bool = False  # needs a base that samples (its draws must differ)
    hidden_objects: bool = False  # needs object-hidden renders from a simulator
    every_step: bool = False  # infers at every env step (its horizon is 1)

    @property
    def description(self) -> str:
        return MODE_DESCRIPTIONS[self.name]

    @property
    def diagnoses(self) -> bool:
        """Whether its passes give IDR's diagnostics (E_img, E_prop, R_img, the gate)."""
        return {"no_img", "no_prop"} <= set(self.passes)


THREE = ("factual", "no_img", "no_prop")


def _methods() -> dict[str, Method]:
    table = {
        "baseline": Method("baseline", ("factual",), frozenset({"horizon"})),
        "diagnose": Method("diagnose", THREE, frozenset({"eps", "horizon"})),
        "cfg": Method("cfg", ("factual", "no_img"), frozenset({"w", "horizon"})),
        "ensemble": Method(
            "ensemble", ("factual", "sample"), frozenset({"samples", "horizon"}), sampling=True
        ),
        "temporal": Method("temporal", ("factual",), frozenset({"te_coeff"}), every_step=True),
        "pcd": Method(
            "pcd", ("factual", "no_objects"), frozenset({"w", "horizon"}), hidden_objects=True
        ),
    }
    for mode in REFINER_MODES:
        table[mode] = Method(mode, THREE, _IDR_READS - _UNUSED_BY_ABLATION.get(mode, set()))
    assert set(table) == set(MODES), set(MODES) ^ set(table)
    return {m: table[m] for m in MODES}


METHODS: dict[str, Method] = _methods()


def method_of(cfg: RefinerConfig | str) -> Method:
    return METHODS[cfg if isinstance(cfg, str) else cfg.mode]


def passes(cfg: RefinerConfig) -> tuple[str, ...]:
    """The forwards of one inference of ``cfg``'s method (``ensemble``: ``samples`` of them)."""
    m = method_of(cfg)
    if m.name == "ensemble":
        return ("factual",) + ("sample",) * (cfg.samples - 1)
    return m.passes


def forward_rows(cfg: RefinerConfig, b: int) -> int:
    """Rows one inference of ``b`` observations costs the base."""
    return len(passes(cfg)) * b


def unread_settings(cfg: RefinerConfig, given: Sequence[str]) -> list[str]:
    """Of the settings ``given`` (a grid's axes for this cell), those its method ignores."""
    reads = method_of(cfg).reads
    return [k for k in given if k in SETTINGS and k not in reads]


def refusal(
    cfg: RefinerConfig,
    *,
    samples: bool | None,
    chunk_len: int | None,
    hidden_objects: bool | None,
    base: str,
    suite: str,
) -> str | None:
    """Why ``cfg``'s method cannot run on ``base`` (does it sample? its chunk length) in
    ``suite`` (does it render object-hidden images?); None where it can or where a fact is
    unknown (None)."""
    m = method_of(cfg)
    if m.sampling and samples is False:
        return (
            f"mode {m.name!r} averages chunks drawn with independent noise, but the base "
            f"{base!r} is deterministic at inference: its {cfg.samples} draws would be one "
            "chunk; use it with a sampling base (diffusion, flow matching, X-VLA)"
        )
    if m.every_step and chunk_len is not None and chunk_len < 2:
        return (
            f"mode {m.name!r} averages overlapping action chunks, but the base {base!r} "
            "predicts one action per inference: there is nothing to ensemble"
        )
    if m.hidden_objects and hidden_objects is False:
        return (
            f"mode {m.name!r} contrasts against a render with the task's objects hidden, which "
            f"the suite {suite!r} does not make (a simulator that renders it: env.suite "
            "tabletop); on a robot there is no such render"
        )
    return None


def combine(cfg: RefinerConfig, outputs: Sequence[Any], seed: int = 0) -> tuple[Any, Any]:
    """The chunk to execute from one inference's forwards (``outputs``, in ``passes(cfg)``
    order) and IDR's diagnostics where the method's passes give them (else None).

    ``temporal`` returns the factual chunk: the execution loop averages the chunks."""
    m = method_of(cfg)
    if len(outputs) != len(passes(cfg)):
        raise ValueError(
            f"mode {m.name!r} needs {len(passes(cfg))} forwards {passes(cfg)}, got {len(outputs)}"
        )
    a_base = outputs[0]
    if m.diagnoses:
        return refine(a_base, outputs[1], outputs[2], cfg, seed=seed)
    if m.name in ("cfg", "pcd"):
        contrast = outputs[1]
        return a_base + cfg.w * (a_base - contrast), None
    if m.name == "ensemble":
        total = outputs[0]
        for x in outputs[1:]:
            total = total + x
        return total / len(outputs), None
    return a_base, None  # baseline, temporal


def sample_seeds(step_seed: int, samples: int) -> list[int]:
    """The noise seeds of an ensemble's draws: the step seed first (the factual pass's, so the
    first draw is the baseline's chunk), then independent ones derived from it."""
    extra = np.random.SeedSequence([step_seed, 0x5EED]).generate_state(samples - 1)
    return [step_seed, *(int(s) & 0x7FFFFFFF for s in extra)]
