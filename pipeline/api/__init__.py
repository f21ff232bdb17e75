"""idr-eval from Python: the stable entry points (docs/python-api.md).

- :func:`evaluate`: one run as ``idr-eval run`` makes it, returning a :class:`RunResult`
  (episode and step tables, calibration, the report's data); :func:`open_run` reads one made
  earlier.
- :func:`diagnose`: E_img, E_prop and R_img of a lerobot policy (a checkpoint folder or an
  object in memory) on given frames, as a :class:`Diagnosis`.

Everything named in ``__all__`` keeps its name, its parameters and the fields it returns
within a major version; other modules of ``pipeline`` are internal.
"""

from __future__ import annotations

from pipeline.api.diagnose import DEFAULT_INTERVENTION, Diagnosis, diagnose
from pipeline.api.offline import hf_offline
from pipeline.api.run import EvaluationInterrupted, ReportData, RunResult, evaluate, open_run
from pipeline.errors import ConfigError, RunError

__all__ = [
    "DEFAULT_INTERVENTION",
    "ConfigError",
    "Diagnosis",
    "EvaluationInterrupted",
    "ReportData",
    "RunError",
    "RunResult",
    "diagnose",
    "evaluate",
    "hf_offline",
    "open_run",
]
