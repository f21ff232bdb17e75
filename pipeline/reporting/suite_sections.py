"""Report sections a suite contributes: each is a function of the run's episodes that returns
its Markdown lines, or none where the run holds no episode of its suite. The report's core
(``pipeline.reporting.markdown``) calls them in this order and knows none of them by name."""

from __future__ import annotations

from collections.abc import Callable

import pandas as pd

from pipeline.reporting import libero_pro

SuiteSection = Callable[[pd.DataFrame], list[str]]

#: LIBERO-PRO: success by original suite x perturbation family, paired against the original
SECTIONS: tuple[SuiteSection, ...] = (libero_pro.section,)


def suite_sections(episodes: pd.DataFrame) -> list[str]:
    return [line for section in SECTIONS for line in section(episodes)]
