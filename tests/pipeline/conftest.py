"""Fixtures of the pipeline tests: the fault log that the fault tests write their outcomes to."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

import pytest

REPORT_ENV = "IDR_FAULT_REPORT"  # set by benchmarks/fault_report.py: where to write the records


@pytest.fixture(scope="session")
def _fault_records():
    records: list[dict[str, Any]] = []
    yield records
    target = os.environ.get(REPORT_ENV)
    if target and records:
        Path(target).write_text(json.dumps(records, indent=2))


class FaultLog:
    """One test's measured outcome, for the fault table of the README."""

    def __init__(self, records: list[dict[str, Any]], test: str) -> None:
        self._records, self._test, self._t0 = records, test, time.monotonic()

    def record(self, fault: str, injected: str, guaranteed: str, outcome: dict[str, Any]) -> None:
        self._records.append(
            {
                "fault": fault,
                "injected": injected,
                "guaranteed": guaranteed,
                "outcome": outcome,
                "test": self._test,
                "seconds": round(time.monotonic() - self._t0, 1),
            }
        )


@pytest.fixture
def fault_log(_fault_records, request) -> FaultLog:
    return FaultLog(_fault_records, request.node.nodeid)
