"""MkDocs hook: each suite's ``env.params`` table, rendered from the env class's constructor.

A page asks for a table with a line of its own, ``<!-- params: SUITE -->`` (a registered suite
name); the line is replaced by the rows ``workers.params_model.param_docs`` reads off the
suite's class: the name, type, default and ``Doc`` of each parameter. The same signature is the
model the pre-flight checks ``env.params`` against, so the table cannot drift from what is
accepted. A suite whose class takes keywords it passes on says so in a last row. An unknown
suite, or a parameter without a ``Doc``, fails the build.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING

from mkdocs.exceptions import PluginError

if TYPE_CHECKING:
    from mkdocs.config.defaults import MkDocsConfig
    from mkdocs.structure.files import Files
    from mkdocs.structure.pages import Page

MARKER = re.compile(r"^<!--\s*params:\s*(.*?)\s*-->[ \t]*$", re.MULTILINE)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def render(suite: str) -> str:
    """The Markdown table of ``suite``'s env.params."""
    from workers.envs.factory import ENVS, env_class
    from workers.params_model import param_docs, takes_any_keyword

    if suite not in ENVS:
        raise PluginError(f"params: {suite!r} is not a registered suite ({sorted(ENVS)})")
    cls = env_class(suite)
    rows = param_docs(cls)
    missing = [r.name for r in rows if not r.doc]
    if missing:
        raise PluginError(
            f"params: {suite}: {missing} have no Doc in {cls.__module__}.{cls.__name__}.__init__"
        )
    lines = ["| `env.params` | type | default | |", "|---|---|---|---|"]
    lines += [
        f"| `{r.name}` | `{_cell(r.type)}` | `{_cell(r.default)}` | {_cell(r.doc)} |" for r in rows
    ]
    if takes_any_keyword(cls):
        lines.append("| any other | | | passed on to the env's own config, which checks it |")
    return "\n".join(lines)


def on_page_markdown(
    markdown: str, page: Page | None, config: MkDocsConfig | None, files: Files | None
) -> str:
    """MkDocs event: replace every params marker of the page by its table."""
    where = page.file.src_uri if page is not None else "<markdown>"

    def one(m: re.Match[str]) -> str:
        try:
            return render(m.group(1))
        except PluginError as e:
            raise PluginError(f"{where}: {e}") from e

    return MARKER.sub(one, markdown)
