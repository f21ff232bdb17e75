"""Where modules went when workers/ was laid out by concern, so an entry point written for the old layout
(``env.suite: workers.envs.tabletop:TabletopEnv``) still loads, with a warning naming the new one.

The harness's own modules are not a public API; configs name suites and backbones by their registry
names. This map only keeps ``module:Class`` strings working that users copied from our sources.
"""

from __future__ import annotations

MODULES: dict[str, str] = {
    "workers.backbones.remote": "workers.backbones.websocket",
    "workers.envs.calvin": "workers.envs.suites.calvin.env",
    "workers.envs.libero": "workers.envs.suites.libero.env",
    "workers.envs.libero_assets": "workers.envs.suites.libero.assets",
    "workers.envs.libero_protocol": "workers.envs.suites.libero.protocol",
    "workers.envs.perturbations": "workers.envs.wrappers.perturbations",
    "workers.envs.remote": "workers.envs.server.client",
    "workers.envs.server": "workers.envs.server.serve",
    "workers.envs.simpler": "workers.envs.suites.simpler.env",
    "workers.envs.simpler_protocol": "workers.envs.suites.simpler.protocol",
    "workers.envs.stability": "workers.envs.mujoco.stability",
    "workers.envs.tabletop": "workers.envs.suites.tabletop.env",
    "workers.envs.tabletop_layout": "workers.envs.suites.tabletop.layout",
    "workers.envs.tabletop_sim": "workers.envs.suites.tabletop.sim",
    "workers.envs.vulkan_cpu": "workers.envs.suites.simpler.vulkan_cpu",
    "workers.envs.wire": "workers.envs.server.wire",
}

CLASSES: dict[str, str] = {
    "RemoteEnv": "EnvServerClient",
    "RemoteBackbone": "WebsocketBackbone",
    "RemotePolicy": "PolicyServiceClient",
}
