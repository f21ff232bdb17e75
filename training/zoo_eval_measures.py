"""One evaluation of a saved checkpoint (``training.zoo_evaluator``): open-loop reliance on the
held-out frames and, at every k-th, a closed-loop diagnose cell; each part's figures or its
error, and the CPU it cost."""

from __future__ import annotations

import contextlib
import json
import resource
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from training.zoo_benchmarks import BENCHMARKS, ROOT
from training.zoo_eval_layout import CLOSED_LOOP_CONFIG, CONTROL, HELDOUT, log

if TYPE_CHECKING:
    from pipeline.api.frames import FrameSet


# --- one evaluation --------------------------------------------------------------------------


def cpu_seconds() -> float:
    """This process's CPU seconds, its waited-for children's included."""
    own, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def openloop_metrics(checkpoint: Path, frameset: FrameSet) -> dict[str, float]:
    """Open-loop reliance of the checkpoint on the frames, with the default interventions."""
    from idr_core.interventions import InterventionConfig

    from pipeline.api.reliance import measure
    from pipeline.reporting.reliance import summarize

    fig = summarize(measure(checkpoint, frameset, InterventionConfig()))
    return {
        "openloop_r_img": fig["r_img"],
        "openloop_r_img_lo": fig["ci95"][0],
        "openloop_r_img_hi": fig["ci95"][1],
        "openloop_e_img": fig["e_img"],
        "openloop_e_prop": fig["e_prop"],
    }


def closed_loop_overrides(
    benchmark: str,
    checkpoint: Path,
    episodes: int,
    device: str = "cpu",
    extra: tuple[str, ...] = (),
) -> tuple[Path, list[str]]:
    """The zoo config and overrides of the closed-loop diagnose cell of ``checkpoint``."""
    config, fit = CLOSED_LOOP_CONFIG[benchmark]
    return ROOT / config, [
        f"backbone.params.path={checkpoint}",
        f"backbone.params.device={device}",
        *fit,
        f"episodes_per_task={episodes}",
        "grid=[{mode: [diagnose]}]",
        "tracking.enabled=false",
        "executor.kind=inline",
        "executor.workers=1",
        *extra,
    ]


def closedloop_metrics(run_dir: Path) -> dict[str, float]:
    """Success of the diagnose cell with its Wilson interval and its R_img (the ratio of mean
    effects, 95% interval resampling episodes), both without the image-zeroed control, whose
    success is ``success_control``; error episodes are left out and counted."""
    from pipeline.reporting.run_data import load_run, reference_diagnose
    from pipeline.results.aggregate import wilson
    from pipeline.results.observation_stats import pooled_effects, without_control

    data = load_run(run_dir)
    eps = data.episodes
    errors = int(eps["error"].notna().sum())
    ok = eps[eps["error"].isna()]
    control = ok["task_id"].astype(str).str.contains(CONTROL, regex=False)
    main = ok[~control]
    wins, n = int(main["success"].sum()), len(main)
    lo, hi = wilson(wins, n)
    out = {
        "success_diagnose": wins / n if n else float("nan"),
        "success_lo": lo,
        "success_hi": hi,
        "closedloop_episodes": float(n),
        "closedloop_errors": float(errors),
    }
    if control.any():
        out["success_control"] = float(ok[control]["success"].mean())
    diag = reference_diagnose(data.steps)
    if diag is not None:
        steps = data.steps[data.steps["cell_id"] == diag].dropna(subset=["e_img", "e_prop"])
        fig = pooled_effects(without_control(steps))
        out["closedloop_r_img"] = fig["r_img"]
        out["closedloop_r_img_lo"], out["closedloop_r_img_hi"] = fig["r_img_ci95"]
    return out


@dataclass
class Evaluation:
    """The evaluation of one checkpoint: open loop always, closed loop at steps that are
    multiples of ``every`` x ``closed_loop_every``. The frames are read once per process."""

    benchmark: str
    every: int
    frames: Path
    evals: Path
    frames_every: int = 1
    closed_loop_every: int = 5
    closed_loop_episodes: int = 20
    closed_loop_set: tuple[str, ...] = ()
    device: str = "cpu"
    on_frames: Callable[[FrameSet], None] | None = None  # told once the frames are read
    _frameset: FrameSet | None = field(default=None, repr=False)

    def frameset(self) -> FrameSet:
        """The frames, read at the first evaluation (an evaluator with nothing to evaluate, as
        after a resume, reads none); a failure is the step's error and is tried again."""
        if self._frameset is None:
            from pipeline.api.frames import dataset_frames

            self._frameset = dataset_frames(self.frames, every=self.frames_every)
            if self.on_frames is not None:
                self.on_frames(self._frameset)
        return self._frameset

    def closed_loop_due(self, step: int) -> bool:
        k = self.closed_loop_every
        return k > 0 and step % (self.every * k) == 0

    def __call__(self, step: int, checkpoint: Path) -> dict[str, Any]:
        ran, metrics, errors = ["openloop"], {}, {}
        try:
            metrics.update(openloop_metrics(checkpoint, self.frameset()))
        except Exception as e:
            log(traceback.format_exc())
            errors["openloop"] = describe(e)
        if self.closed_loop_due(step):
            ran.append("closedloop")
            try:
                metrics.update(self.closed_loop(step, checkpoint))
            except Exception as e:
                log(traceback.format_exc())
                errors["closedloop"] = describe(e)
        return {"ran": ran, "metrics": metrics, "errors": errors}

    def prepare(self) -> None:
        """Read the frames before the first evaluation is timed (its CPU seconds are the
        checkpoint's, not the frames'); a failure is left to the evaluation to record."""
        with contextlib.suppress(Exception):
            self.frameset()

    def closed_loop(self, step: int, checkpoint: Path) -> dict[str, float]:
        from pipeline.api import evaluate
        from pipeline.errors import ConfigError
        from pipeline.rundir import read_run_json

        config, overrides = closed_loop_overrides(
            self.benchmark,
            checkpoint,
            self.closed_loop_episodes,
            self.device,
            self.closed_loop_set,
        )
        out = self.evals / f"step_{step:06d}"
        try:
            evaluate(config, out, overrides, echo=log)  # an interrupted one resumes here
        except ConfigError as e:
            if read_run_json(out) is None:
                raise  # a fresh run dir refused: the config itself is bad
            # an interrupted evaluation that may not be resumed (another code version, CPU
            # class or config): it is kept aside, never mixed, and the step runs afresh
            aside = set_aside(out)
            log(f"step {step}: {e}; its closed loop starts afresh (kept in {aside})")
            evaluate(config, out, overrides, echo=log)
        return closedloop_metrics(out)


def set_aside(run_dir: Path) -> Path:
    """Rename ``run_dir`` to the first free ``<name>.superseded-K`` beside it."""
    k = 1
    while (aside := run_dir.with_name(f"{run_dir.name}.superseded-{k}")).exists():
        k += 1
    run_dir.rename(aside)
    return aside


def describe(e: BaseException) -> str:
    return f"{type(e).__name__}: {e}"


# --- the settings the measures need, checked before training starts ----------------------


def check_closed_loop_config(benchmark: str, closed_loop_set: tuple[str, ...]) -> None:
    """Refuse a closed-loop config that does not load (a ``--closed-loop-set`` of an unknown key
    or a bad value); what only the pre-flight of a checkpoint can check (an env parameter's
    type) is the first closed loop's error, recorded against its step."""
    from pipeline.api.run import load
    from pipeline.errors import ConfigError

    config, overrides = closed_loop_overrides(
        benchmark, Path("checkpoint"), 1, "cpu", closed_loop_set
    )
    try:
        load(config, overrides)
    except ConfigError as e:
        raise SystemExit(
            f"--closed-loop-set {list(closed_loop_set)}: the closed-loop config "
            f"{config.relative_to(ROOT)} does not load with it: {e}"
        ) from None


def check_eval_settings(
    benchmark: str,
    every: int,
    save_freq: int | None,
    frames: Path,
    frames_every: int,
    closed_loop_every: int,
    closed_loop_episodes: int,
    tracking_uri: str | None,
    flag: str = "eval-",
    closed_loop_set: tuple[str, ...] = (),
) -> None:
    """Refuse, before any work, settings the evaluator cannot run with (SystemExit naming the
    flag and the fix). ``flag``: ``eval-`` for `zoo train`'s spelling, empty for the module's."""
    every_flag = f"--{flag}every" if flag else "--every"
    if every < 1 or (save_freq is not None and every % save_freq):
        raise SystemExit(
            f"{every_flag} {every}: give a positive multiple of the save frequency "
            f"({save_freq}, --save-freq), e.g. {every_flag} {save_freq or 1}; only saved "
            "checkpoints can be evaluated"
        )
    if closed_loop_every < 0:
        raise SystemExit(
            f"--closed-loop-every {closed_loop_every}: give 0 (no closed loop) or a positive k "
            "(a closed-loop cell at every k-th evaluated checkpoint)"
        )
    if closed_loop_every and closed_loop_episodes < 1:
        raise SystemExit(
            f"--closed-loop-episodes {closed_loop_episodes}: give at least 1 episode per task "
            "(20 give a success interval narrower than +-25 pp), or --closed-loop-every 0"
        )
    if frames_every < 1:
        raise SystemExit(f"--{flag or ''}frames-every {frames_every}: give 1 or more")
    frames_flag = f"--{flag}frames" if flag else "--frames"
    info = frames / "meta" / "info.json"
    if not info.is_file():
        raise SystemExit(
            f"{frames_flag} {frames}: no LeRobotDataset of held-out demonstrations there "
            f"(meta/info.json missing); record the {benchmark} ones with `"
            f"{HELDOUT[benchmark][1]}`, or point {frames_flag} at such a dataset"
        )
    have = {k: list(v["shape"]) for k, v in json.loads(info.read_text())["features"].items()}
    want = BENCHMARKS[benchmark].features
    wrong = [
        f"{k}: wants {s}, frames have {have.get(k)}" for k, s in want.items() if have.get(k) != s
    ]
    if wrong:
        raise SystemExit(
            f"{frames_flag} {frames} does not fit the {benchmark} members ({'; '.join(wrong)}); "
            f"record them with `{HELDOUT[benchmark][1]}` or pick --benchmark"
        )
    if closed_loop_every:
        check_closed_loop_config(benchmark, closed_loop_set)
    if tracking_uri is not None:
        from pipeline.tracking.backend import check_uri

        try:
            check_uri(tracking_uri)
        except RuntimeError as e:
            raise SystemExit(f"--{flag}tracking-uri: {e}") from None
