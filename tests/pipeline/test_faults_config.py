"""Fault 6, bad configuration, fuzzed (hypothesis): every invalid value of every config field,
as a CLI override, and every unknown key, parameter, suite or task, gives one clear error
naming the field (exit 2), never a traceback, and never starts an actor. Random override
strings and random config files never give a traceback either."""

from __future__ import annotations

import json
import string
from collections import Counter
from pathlib import Path
from typing import Annotated, Any, Literal, Union, get_args, get_origin

import pytest
from annotated_types import Ge, Gt, Le
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from pipeline import cli
from pipeline.planning.config import RunConfig
from pipeline.planning.executor_config import SHARED_ONLY

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "conf" / "smoke.yaml")
FUZZ = settings(
    max_examples=80,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
# strings pydantic reads as a bool, or a number (for int / float fields)
BOOLISH = {"0", "off", "f", "false", "n", "no", "1", "on", "t", "true", "y", "yes"}
NUMBERISH = {"inf", "infinity", "nan", "e"}


STATS: Counter[str] = Counter()  # over the whole module, for the fault report


class _WouldStart(BaseException):
    """Raised where a run would start its actors: validation let the input through."""


def _fields(model: type[BaseModel] = RunConfig, prefix: str = "") -> list[tuple[str, FieldInfo]]:
    """Every field, also those of each variant of a discriminated union (``executor``): its
    discriminator once, with every variant's tag."""
    out = []
    for name, f in model.model_fields.items():
        path = f"{prefix}{name}"
        out.append((path, f))
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel):
            out += _fields(f.annotation, f"{path}.")
        elif isinstance(f.discriminator, str):
            variants = get_args(f.annotation)
            tags = [
                t for v in variants for t in get_args(v.model_fields[f.discriminator].annotation)
            ]
            out.append((f"{path}.{f.discriminator}", FieldInfo.from_annotation(Literal[*tags])))
            for variant in variants:
                seen = {p for p, _ in out}
                out += [(p, g) for p, g in _fields(variant, f"{path}.") if p not in seen]
    return out


FIELDS = _fields()
words = st.text(string.ascii_letters + "_", min_size=1, max_size=10)
junk_text = words.filter(lambda s: s.lower() not in BOOLISH | NUMBERISH)
int_lists = st.lists(st.integers(-5, 5), min_size=1, max_size=3)
mappings = st.dictionaries(words, st.integers(), min_size=1, max_size=2)


def _bound(f: FieldInfo, kind: type) -> Any:
    return next(
        (getattr(m, kind.__name__.lower()) for m in f.metadata if isinstance(m, kind)), None
    )


def invalid_values(path: str, f: FieldInfo) -> st.SearchStrategy[Any]:
    """Values that the schema must refuse for this field (None is left out: often allowed)."""
    ann = f.annotation
    if get_origin(ann) in (Union, type(int | None)):
        ann = next(a for a in get_args(ann) if a is not type(None))
    finite = True  # the config models refuse inf and nan unless a field allows them (idr.tau)
    if get_origin(ann) is Annotated:
        ann, *meta = get_args(ann)
        finite = not any(getattr(m, "allow_inf_nan", False) for m in meta)
    if isinstance(ann, type) and issubclass(ann, BaseModel):
        return st.one_of(st.integers(), junk_text, int_lists)
    if get_origin(ann) is Literal:
        return st.one_of(
            junk_text.filter(lambda s: s not in get_args(ann)), st.integers(), int_lists
        )
    if ann is bool:
        return st.one_of(junk_text, st.integers(2, 10**6), int_lists, mappings)
    if ann in (int, float):
        options = [junk_text, int_lists, mappings]
        if finite:
            options.append(st.just(float("inf")))
        if ann is int:
            options.append(st.floats(0.1, 1e6).filter(lambda x: not x.is_integer()))
        for kind, shift in ((Ge, -1), (Gt, 0)):
            low = _bound(f, kind)
            if low is not None:
                options.append(st.integers(max_value=int(low) + shift))
        high = _bound(f, Le)
        if high is not None:
            options.append(st.integers(min_value=high + 1))
        return st.one_of(*options)
    if ann is str:
        options = [st.integers(), int_lists, mappings]
        if path == "name":  # one path component: no '/', no '..'
            options += [
                st.just(".."),
                words.map(lambda w: f"../{w}"),
                words.map(lambda w: f"a/{w}"),
            ]
        return st.one_of(*options)
    if get_origin(ann) is dict:
        return st.one_of(st.integers(), junk_text, int_lists)
    if get_origin(ann) is list:
        item = get_args(ann)[0]
        bad_item = st.integers() if item is str else st.integers(-5, 5)
        return st.one_of(st.integers(), junk_text, st.lists(bad_item, min_size=1, max_size=3))
    raise AssertionError(f"no invalid-value strategy for {path}: {ann}")


@pytest.fixture
def run_cli(tmp_path, monkeypatch, capsys):
    """``idr-eval run conf/smoke.yaml --out ... OVERRIDES`` in this process, with every way to
    start work replaced by a tripwire; returns (exit code or 'started', stderr)."""
    import pipeline.execution.cluster
    import pipeline.execution.runner
    import pipeline.execution.scheduler
    import workers.episode.worker

    def tripwire(*args: object, **kwargs: object) -> None:
        raise _WouldStart

    monkeypatch.setattr(pipeline.execution.runner, "execute", tripwire)
    monkeypatch.setattr(pipeline.execution.scheduler.Scheduler, "run_stage", tripwire)
    monkeypatch.setattr(workers.episode.worker.EpisodeWorker, "__init__", tripwire)
    monkeypatch.setattr(pipeline.execution.cluster, "init_ray", tripwire)
    out = tmp_path / "run"

    def run(*overrides: str, config: str = SMOKE) -> tuple[int | str, str]:
        try:
            code: int | str = cli.main(["run", config, "--out", str(out), *overrides])
        except SystemExit as e:  # argparse's own usage error: one line, exit 2
            code = e.code
        except _WouldStart:
            code = "started"
        err = capsys.readouterr().err
        STATS["inputs"] += 1
        STATS["tracebacks"] += "Traceback" in err
        assert "Traceback" not in err
        assert not out.exists(), "an invalid config created its RUN_DIR"
        STATS["refused (exit 2, one error)" if code == 2 else "accepted (random but valid)"] += 1
        return code, err

    return run


def _assert_one_clear_error(result: tuple[int | str, str], *names: str) -> None:
    code, err = result
    STATS["actors_started_by_invalid_input"] += code == "started"
    assert code == 2, f"accepted: {code} {err}"
    assert err.count("idr-eval: error:") == 1, err
    for name in names:
        assert name in err, f"{name!r} not named in: {err}"


@FUZZ
@given(data=st.data())
def test_every_invalid_field_value_is_one_clear_error(run_cli, data) -> None:
    path, field = data.draw(st.sampled_from(FIELDS), label="field")
    value = data.draw(invalid_values(path, field), label="value")
    # a shared policy's key: checked in a run that has one (an in_actor run refuses any value)
    shared = path.startswith("executor.") and path.split(".")[1] in SHARED_ONLY
    placement = ["executor.policy=shared"] if shared else []
    _assert_one_clear_error(run_cli(*placement, f"{path}={json.dumps(value)}"), path)


SECTIONS = [
    "",
    *(
        p + "."
        for p, f in FIELDS
        if (isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel))
        or isinstance(f.discriminator, str)
    ),
]


@FUZZ
@given(section=st.sampled_from(SECTIONS), key=words, value=st.integers())
def test_unknown_keys_are_named(run_cli, section, key, value) -> None:
    known = {p for p, _ in FIELDS}
    if f"{section}{key}" in known:
        return
    _assert_one_clear_error(run_cli(f"{section}{key}={value}"), f"{section}{key}: unknown key")


def _params_of(where: str) -> list[str]:
    """The constructor parameters of smoke.yaml's fake backbone or fake env."""
    from inspect import signature

    from workers.backbones.factory import BACKBONES
    from workers.envs.factory import ENVS
    from workers.registry import load_class

    cls = load_class(BACKBONES if where == "backbone" else ENVS, "fake_marker", where)
    return [n for n in signature(cls).parameters if n != "self"]


@FUZZ
@given(
    case=st.sampled_from(["backbone.kind", "env.suite", "env.tasks", "params_key", "params_type"]),
    where=st.sampled_from(["backbone", "env"]),
    word=junk_text,
    data=st.data(),
)
def test_refusals_after_the_schema_name_the_field(run_cli, case, where, word, data) -> None:
    """Valid by the schema, refused while planning: still one error naming the field."""
    if case in ("backbone.kind", "env.suite"):
        if word in ("fake_marker", "noop", "lerobot", "tabletop", "libero", "tabletop_expert"):
            return
        _assert_one_clear_error(run_cli(f"{case}={json.dumps(word)}"), f"{case}={word!r}")
    elif case == "env.tasks":
        result = run_cli(f"env.tasks=[reach, {json.dumps(word)}]")
        _assert_one_clear_error(result, "env.tasks", word)
    elif case == "params_key":
        if word in _params_of(where):
            return
        _assert_one_clear_error(run_cli(f"{where}.params.{word}=1"), f"{where}.params", word)
    else:  # a known parameter with a value its type hint refuses
        name = data.draw(
            st.sampled_from(["image_size"] if where == "env" else ["gain", "chunk_len"])
        )
        _assert_one_clear_error(
            run_cli(f"{where}.params.{name}={json.dumps(word)}"), f"{where}.params", name
        )


@FUZZ
@given(text=st.text(max_size=40))
def test_random_overrides_never_give_a_traceback(run_cli, text) -> None:
    code, err = run_cli(text if "=" in text else f"{text}=1")
    assert code in (2, "started"), err
    if code == 2:
        assert err.count("error:") == 1, err


@FUZZ
@given(text=st.text(max_size=200))
def test_random_config_files_never_give_a_traceback(run_cli, tmp_path, text) -> None:
    config = tmp_path / "fuzz.yaml"
    config.write_text(text)
    code, err = run_cli(config=str(config))
    assert code == 2 and err.count("idr-eval: error:") == 1, err


def test_fuzz_summary(fault_log) -> None:
    """Runs last in this module: records what the properties above measured, and fails if
    any input gave a traceback or started work while refused as invalid."""
    if not STATS["inputs"]:
        pytest.skip("the fuzz tests of this module did not run (selected alone)")
    assert STATS["tracebacks"] == 0 and STATS["actors_started_by_invalid_input"] == 0, STATS
    fault_log.record(
        "bad configuration (fuzzed)",
        "hypothesis: invalid values for every config field, unknown keys, unknown suites, "
        "tasks and params, wrong param types, random overrides and config files",
        "one error naming the field (exit 2), no traceback, no actor started",
        {
            **STATS,
            "tracebacks": STATS["tracebacks"],
            "actors_started_by_invalid_input": STATS["actors_started_by_invalid_input"],
        },
    )
