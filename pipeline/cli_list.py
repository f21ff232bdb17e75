"""``idr-eval list``: what a config can name (suites, lerobot env types, a suite's tasks,
perturbation kinds, backbones)."""

from __future__ import annotations

import argparse

from pipeline.errors import ConfigError


def _table(rows: list[tuple[object, ...]]) -> str:
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows
    )


def _cmd_list(args: argparse.Namespace) -> int:
    from pipeline.planning import catalog
    from pipeline.planning.config_yaml import safe_load_yaml

    what = args.what
    if what == "tasks":
        if not args.suite:
            raise ConfigError("idr-eval list tasks SUITE [key=value ...]: name a suite")
        params = {}
        for item in args.params:
            key, eq, value = item.partition("=")
            if not eq:
                raise ConfigError(f"{item!r}: env params are key=value")
            params[key] = safe_load_yaml(value)
        rows = catalog.tasks(args.suite, params)
        print(_table([("task", "name", "max steps"), *rows]))
        return 0
    sections = {
        "suites": lambda: [("suite", "what"), *catalog.suites()],
        "envs": lambda: [
            ("lerobot type", "needs", "installed", "note"),
            *[(t, m, "yes" if ok else "no", n) for t, m, ok, n in catalog.lerobot_env_types()],
        ],
        "perturbations": lambda: [("kind", "what", "suites"), *catalog.perturbation_kinds()],
        "backbones": lambda: [("backbone", "class"), *catalog.backbones()],
    }
    for name in [what] if what != "all" else list(sections):
        print(f"# {name}")
        print(_table(sections[name]()))
        print()
    return 0


def add_list(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ls = sub.add_parser(
        "list",
        help="what a config can name: suites, lerobot env types (installed or not), a suite's "
        "tasks (list tasks SUITE key=value ...), perturbation kinds, backbones",
    )
    ls.add_argument(
        "what",
        nargs="?",
        default="all",
        choices=["all", "suites", "envs", "tasks", "perturbations", "backbones"],
    )
    ls.add_argument("suite", nargs="?", help="list tasks: the suite")
    ls.add_argument("params", nargs="*", help="list tasks: env params as key=value")
    ls.set_defaults(func=_cmd_list)
