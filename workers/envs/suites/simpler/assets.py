"""What a SIMPLER episode loads, and where: the ManiSkill2_real2sim checkout and the files under
its ``data/`` that each episode's env needs (paths read off its task envs, ManiSkill2_real2sim
ef7a4d4), so that a missing one is refused before any episode instead of failing it quietly.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

from workers.envs.suites.simpler.protocol import Episode

CHECKOUT_HINT = (
    "point env.params.maniskill2_real2sim (or $MS2_REAL2SIM, or $SIMPLER_ENV with its "
    "ManiSkill2_real2sim submodule) at a checkout of github.com/simpler-env/ManiSkill2_real2sim "
    "with its data/ (git lfs is not used: plain git files)"
)


MODEL_JSONS = {  # the env's model database; every key of it is checked when no model_ids are given
    "GraspSingleOpenedCokeCanInScene-v0": "custom/info_pick_custom_v0.json",
    "GraspSingleOpenedCokeCanDistractorInScene-v0": "custom/info_pick_custom_v0.json",
    "MoveNearGoogleInScene-v0": "custom/info_pick_custom_v0.json",
    "MoveNearGoogleBakedTexInScene-v0": "custom/info_pick_custom_baked_tex_v0.json",
    "PlaceIntoClosedTopDrawerCustomInScene-v0": "custom/info_pick_custom_baked_tex_v1.json",
    "PutSpoonOnTableClothInScene-v0": "custom/info_bridge_custom_v0.json",
    "PutCarrotOnPlateInScene-v0": "custom/info_bridge_custom_v0.json",
    "StackGreenCubeOnYellowCubeBakedTexInScene-v0": "custom/info_bridge_custom_baked_tex_v0.json",
    "PutEggplantInBasketScene-v0": "custom/info_bridge_custom_v0.json",
}
LOADED_MODELS = {  # the models an env puts in its scene (all its episodes together)
    "GraspSingleOpenedCokeCanInScene-v0": ("opened_coke_can",),
    "GraspSingleOpenedCokeCanDistractorInScene-v0": ("opened_coke_can",),
    "MoveNearGoogleBakedTexInScene-v0": (
        "blue_plastic_bottle",
        "baked_opened_pepsi_can",
        "orange",
        "baked_opened_7up_can",
        "baked_apple",
        "baked_sponge",
        "baked_opened_coke_can",
        "baked_opened_redbull_can",
    ),
    "MoveNearGoogleInScene-v0": (
        "blue_plastic_bottle",
        "opened_pepsi_can",
        "orange",
        "opened_7up_can",
        "apple",
        "sponge",
        "opened_coke_can",
        "opened_redbull_can",
    ),
    "PutSpoonOnTableClothInScene-v0": (
        "bridge_spoon_generated_modified",
        "table_cloth_generated_shorter",
    ),
    "PutCarrotOnPlateInScene-v0": (
        "bridge_carrot_generated_modified",
        "bridge_plate_objaverse_larger",
    ),
    "StackGreenCubeOnYellowCubeBakedTexInScene-v0": (
        "baked_green_cube_3cm",
        "baked_yellow_cube_3cm",
    ),
    "PutEggplantInBasketScene-v0": ("eggplant", "dummy_sink_target_plane", "sink"),
}
CHECKED_ONLY = ("Drawer",)  # drawer envs check every model folder's collision.obj, load none
DISTRACTORS = {  # grasp_single_in_scene.py: distractor_config less (default) / more
    "less": ("opened_pepsi_can", "apple", "sponge", "orange"),
    "more": (
        "opened_7up_can",
        "opened_sprite_can",
        "sponge",
        "orange",
        "opened_fanta_can",
        "bridge_spoon_generated_modified",
    ),
}
VISUALS = ("textured.obj", "textured.dae", "textured.glb")  # the first that exists is loaded


def episode_assets(ep: Episode, model_keys: dict[str, list[str]]) -> list[str]:
    """Paths (under data/) the episode's env needs: the stage, the cabinet, the overlay, the
    model json, every model folder's ``collision.obj`` the env checks (``model_keys``: model
    json -> its keys, read from the checkout), and ``<folder>/textured.*`` for the models it
    loads (any of VISUALS)."""
    build = dict(ep.build)
    paths = []
    if not ep.scene.startswith("dummy"):
        paths.append(f"hab2_bench_assets/stages/{ep.scene}.glb")
    if "Drawer" in ep.env_id:
        paths.append(f"custom/{build.get('station_name', 'mk_station')}.urdf")
    if ep.overlay:
        paths.append(f"real_inpainting/{ep.overlay}")
    json_file = MODEL_JSONS.get(ep.env_id, "custom/info_pick_custom_v0.json")
    paths.append(json_file)
    if "model_ids" in build:
        loaded: tuple[str, ...] = (str(build["model_ids"]),)
        checked = loaded
    else:
        loaded = LOADED_MODELS.get(ep.env_id, ())
        if "Distractor" in ep.env_id:
            loaded += DISTRACTORS[str(build.get("distractor_config", "less"))]
        forced = ep.env_id.startswith("GraspSingle")  # it passes its own model_ids
        checked = loaded if forced else tuple(model_keys.get(json_file, ())) + loaded
    paths += [f"custom/models/{m}/collision.obj" for m in dict.fromkeys(checked)]
    if not any(k in ep.env_id for k in CHECKED_ONLY) or "model_ids" in build:
        paths += [f"custom/models/{m}/textured.*" for m in dict.fromkeys(loaded)]
    return paths


def checkout(path: str | None = None) -> Path:
    """The ManiSkill2_real2sim checkout; ValueError naming the fix."""
    root = path or os.environ.get("MS2_REAL2SIM")
    if not root and os.environ.get("SIMPLER_ENV"):
        root = str(Path(os.environ["SIMPLER_ENV"]) / "ManiSkill2_real2sim")
    if not root:
        raise ValueError(f"env.params.maniskill2_real2sim is not set: {CHECKOUT_HINT}")
    p = Path(root).expanduser()
    if not (p / "mani_skill2_real2sim" / "envs").is_dir():
        raise ValueError(f"env.params.maniskill2_real2sim={root}: not a checkout; {CHECKOUT_HINT}")
    return p


def missing_assets(data: Path, episodes: Sequence[Episode]) -> list[str]:
    """The files under ``data`` that these episodes need and lack (a missing stage would
    give a scene without a table: objects fall to z = -18 m and every episode fails)."""
    keys: dict[str, list[str]] = {}
    for name in set(MODEL_JSONS.values()) | {"custom/info_pick_custom_v0.json"}:
        f = data / name
        keys[name] = list(json.loads(f.read_text())) if f.is_file() else []
    needed = dict.fromkeys(p for ep in episodes for p in episode_assets(ep, keys))
    missing = []
    for path in needed:
        if path.endswith("/textured.*"):
            folder = data / path.removesuffix("/textured.*")
            if not any((folder / v).is_file() for v in VISUALS):
                missing.append(f"{path.removesuffix('*')}{{obj,dae,glb}}")
        elif not (data / path).is_file():
            missing.append(path)
    return missing
