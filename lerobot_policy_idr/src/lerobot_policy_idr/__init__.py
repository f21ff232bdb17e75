"""IDR (infer-diagnose-refine) as a lerobot policy plugin.

Importing the package registers, with lerobot, the policy type ``idr`` (config, processor
steps) and the tiny VLA (``tiny_vla``): lerobot's tools import it by its name
(``register_third_party_plugins``), and this registration is its only import-time side effect.

The method itself is framework-free: ``refiner`` (the paper's equations on arrays),
``interventions`` (do(V), do(S)) and ``three_pass`` (the batched three-pass inference with
shared noise). idr-eval's harness imports them from here.
"""

from idr_core.refiner import RefinerConfig, refine

from lerobot_policy_idr import processor_idr  # noqa: F401  (registers the processor steps)
from lerobot_policy_idr.configuration_idr import IDRConfig
from lerobot_policy_idr.loading import load_idr
from lerobot_policy_idr.tiny_vla.configuration_tiny_vla import TinyVLAConfig

__all__ = ["IDRConfig", "RefinerConfig", "TinyVLAConfig", "load_idr", "refine"]
