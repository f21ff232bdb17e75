"""A config's YAML: read without aliases (``safe_load_yaml``), dotted ``key=value`` overrides
parsed as YAML and applied (``parse_override``, ``apply_overrides``), written without aliases
(``NoAliasDumper``). What the values mean is ``pipeline.planning.config``'s."""

from __future__ import annotations

import json
from typing import Any

import yaml

from pipeline.errors import ConfigError


class NoAliasLoader(yaml.SafeLoader):
    """YAML without aliases: a 1 KB file of nested aliases ("billion laughs") expands to
    gigabytes once copied or validated; a config has no need for them. Refused while parsing,
    before anything is copied."""

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise ConfigError(
                f"YAML alias *{event.anchor} at line {event.start_mark.line + 1}: aliases (and "
                "anchors used through them) are not accepted in configs, since nested ones "
                "expand exponentially; write the values out"
            )
        return super().compose_node(parent, index)


def safe_load_yaml(text: str) -> Any:
    """``yaml.safe_load`` without aliases (ConfigError on one)."""
    loader = NoAliasLoader(text)  # a SafeLoader: no Python objects are ever constructed
    try:
        return loader.get_single_data()
    finally:
        loader.dispose()


def parse_override(text: str) -> tuple[list[str], Any]:
    if "=" not in text:
        raise ConfigError(
            f"override {text!r} must look like key.sub=value (e.g. executor.workers=4)"
        )
    key, raw = text.split("=", 1)
    path = key.strip().split(".")
    if not all(path):
        raise ConfigError(f"override {text!r} has an empty key part")
    try:
        value = safe_load_yaml(raw)
    except yaml.YAMLError as e:
        why = getattr(e, "problem", None) or str(e).splitlines()[0]  # ReaderError: no .problem
        raise ConfigError(f"override {text!r}: value is not valid YAML ({why})") from None
    return path, value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    data = json.loads(json.dumps(data))  # deep copy of plain data
    for text in overrides:
        path, value = parse_override(text)
        node = data
        for part in path[:-1]:
            child = node.get(part)
            if child is None:
                child = node[part] = {}
            if not isinstance(child, dict):
                raise ConfigError(f"override {text!r}: {part!r} is not a section")
            node = child
        node[path[-1]] = value
    return data


class NoAliasDumper(yaml.SafeDumper):
    def ignore_aliases(self, data: Any) -> bool:
        return True  # a value used twice is written twice: the file loads without aliases
