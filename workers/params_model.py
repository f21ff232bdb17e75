"""A class's params (``env.params``, ``backbone.params``) as a typed model.

The constructor's signature is the one home of every key: its name, its type hint, its default
and, written as ``Annotated[T, Doc("...")]`` (``workers.param_doc``), its documentation. :func:`params_model`
turns it into a pydantic model (unknown keys forbidden unless the constructor takes
``**kwargs``), as lerobot's ``EnvConfig`` dataclasses are draccus's; :func:`check_params`
validates a config's params against it before any work (a typo gets a did-you-mean), and the
docs' parameter tables are rendered from :func:`param_docs` (``docs/hooks/params_tables.py``),
so the table, the check and the constructor cannot drift apart.

The constructor still receives the params as written (a YAML list for a tuple): the model
checks, it does not convert.
"""

from __future__ import annotations

import difflib
import functools
import inspect
import typing
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError, create_model

from workers.param_doc import Doc


@dataclass(frozen=True)
class ParamDoc:
    """One row of a parameter table."""

    name: str
    type: str  # the hint as written, without its Annotated metadata
    default: str  # repr of the default; "required" without one
    doc: str  # its Doc; "" where the constructor gives none


def _forwarded_to(cls: Any) -> Any:
    """The class a constructor's ``**params`` go to, where it says so (``params_forwarded_to``:
    LIBERO-PRO's env takes LIBERO's params); None: they go where it alone knows."""
    return getattr(cls, "params_forwarded_to", None)


def _parameters(cls: Any) -> list[inspect.Parameter]:
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    own = [p for p in inspect.signature(cls).parameters.values() if p.kind in kinds]
    target = _forwarded_to(cls)
    if target is None:
        return own
    names = {p.name for p in own}
    return own + [p for p in _parameters(target) if p.name not in names]


def takes_any_keyword(cls: Any) -> bool:
    """Whether the constructor takes any keyword: ``**kwargs`` it passes on to a class that
    checks them itself (lerobot's env config), not to one it names (``params_forwarded_to``)."""
    target = _forwarded_to(cls)
    if target is not None:
        return takes_any_keyword(target)
    return any(p.kind is p.VAR_KEYWORD for p in inspect.signature(cls).parameters.values())


def _hints(cls: Any) -> dict[str, Any]:
    target = _forwarded_to(cls)
    try:
        own = typing.get_type_hints(cls.__init__, include_extras=True)
    except Exception:  # unresolvable hints: the names are still checked, the types are not
        own = {}
    return {**(_hints(target) if target is not None else {}), **own}


@functools.cache
def params_model(cls: Any) -> type[BaseModel]:
    """The pydantic model of ``cls``'s constructor params (see the module docstring)."""
    hints = _hints(cls)
    fields: dict[str, Any] = {}
    for p in _parameters(cls):
        hint = hints.get(p.name, Any)
        default = ... if p.default is inspect.Parameter.empty else p.default
        fields[p.name] = (hint, default)
    extra = "allow" if takes_any_keyword(cls) else "forbid"
    config = ConfigDict(extra=extra, arbitrary_types_allowed=True, protected_namespaces=())
    return create_model(f"{cls.__name__}Params", __config__=config, **fields)


def named_with_hints(unknown: list[str], accepted: list[str]) -> str:
    """``'colour', 'siz' ('siz': did you mean 'size'?)``: unknown keys, with the accepted key
    each is closest to, where one is close."""
    hints = [
        f"{k!r}: did you mean {close[0]!r}?"
        for k in unknown
        if (close := difflib.get_close_matches(k, accepted, n=1))
    ]
    return ", ".join(map(repr, unknown)) + (f" ({'; '.join(hints)})" if hints else "")


def check_params(where: str, cls: Any, params: dict[str, Any]) -> None:
    """Refuse params the class does not take (did you mean ...?, naming the ones it does) and
    values that do not fit their type, with one ValueError naming ``where`` and the key."""
    accepted = [p.name for p in _parameters(cls)]
    unknown = [] if takes_any_keyword(cls) else [k for k in params if k not in accepted]
    if unknown:
        raise ValueError(
            f"{where}: unexpected parameter {named_with_hints(unknown, accepted)}; "
            f"accepted parameters: {accepted}"
        )
    try:
        model = params_model(cls)
    except Exception:  # a hint pydantic cannot build a model of: names checked, types left
        return
    try:
        model.model_validate(params)
    except ValidationError as e:
        err = e.errors()[0]
        name = ".".join(str(x) for x in err["loc"][:1])
        if err["type"] == "missing":
            raise ValueError(f"{where}: {name} is required") from None
        value = params.get(name, err.get("input"))
        raise ValueError(f"{where}: {name}={value!r} is invalid: {err['msg']}") from None


def _type_text(hint: Any) -> str:
    if typing.get_origin(hint) is typing.Annotated:
        hint = typing.get_args(hint)[0]
    text = hint.__name__ if isinstance(hint, type) else str(hint)
    return text.replace("typing.", "").replace("collections.abc.", "")


def param_docs(cls: Any) -> list[ParamDoc]:
    """The rows of ``cls``'s parameter table, in the constructor's order."""
    hints = _hints(cls)
    rows = []
    for p in _parameters(cls):
        hint = hints.get(p.name, Any)
        doc = ""
        if typing.get_origin(hint) is typing.Annotated:
            for meta in typing.get_args(hint)[1:]:
                if isinstance(meta, Doc):
                    doc = meta.text
        default = "required" if p.default is inspect.Parameter.empty else repr(p.default)
        rows.append(ParamDoc(p.name, _type_text(hint), default, doc))
    return rows
