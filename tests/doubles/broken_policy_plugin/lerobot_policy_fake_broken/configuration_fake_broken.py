"""FAKE plugin config: registers ``fake_broken``, after an import that fails."""

import a_dependency_nobody_installed  # noqa: F401
from lerobot.configs.policies import PreTrainedConfig


@PreTrainedConfig.register_subclass("fake_broken")
class FakeBrokenConfig(PreTrainedConfig):
    pass
