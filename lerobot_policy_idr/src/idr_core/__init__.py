"""The IDR method on arrays, importing neither lerobot nor any model or simulator: the
refiner (the paper's equations), the interventions, the batched three-pass inference with
shared noise, and checks of a lerobot checkpoint folder read from its files.

Shipped in the ``lerobot_policy_idr`` distribution beside the lerobot plugin
(``lerobot_policy_idr``), which registers with lerobot on import; this package stays cheap to
import (no torch, no lerobot) for drivers and tools that only need the method.
"""
