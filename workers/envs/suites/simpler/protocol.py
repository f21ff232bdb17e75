"""SIMPLER's official evaluation protocol as data: tasks, episode lists, action conventions.

Everything here is read off SimplerEnv's evaluation scripts (``scripts/rt1_*.sh``,
``scripts/octo_bridge.sh``), its evaluator (``simpler_env/evaluation/maniskill2_evaluator.py``)
and ManiSkill2_real2sim's task envs, at SimplerEnv 4ab7178 / ManiSkill2_real2sim ef7a4d4;
nothing of theirs is imported or copied. numpy and scipy only: the driver lists tasks and
checks params without SAPIEN.

A task id is ``<SimplerEnv task>/<setup>`` (``google_robot_open_top_drawer/visual_matching``);
episode ``e`` of a task is the ``e``-th episode of the official list, enumerated in the
evaluator's loop order (the scripts' outer loops first: URDF recolour or variant, then robot
x, robot y, robot rotation, then object x, object y or the object episode id). Lists:

======================================  =================  ==================
task                                    visual_matching    variant_agg
======================================  =================  ==================
pick coke can (horizontal/vertical/     100 each           225 each (9 variants
standing)                               (4 URDF x 5 x 5)   x 25 positions)
move near                               240 (4 x 60)       480 (8 x 60)
open/close top/middle/bottom drawer     36 each (4 x 9)    63 each (7 x 9)
put apple into closed top drawer        108 (4 x 3 x 9)    189 (7 x 3 x 9)
WidowX spoon / carrot / stack /         24 each            -
eggplant
======================================  =================  ==================

The camera-angle variants the variant-aggregation scripts also run are left out, as the
official metric (``tools/calc_metrics_evaluation_videos.py``) leaves them out.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

GOOGLE_CONTROL = (
    "arm_pd_ee_delta_pose_align_interpolate_by_planner"
    "_gripper_pd_joint_target_delta_pos_interpolate_by_planner"
)
WIDOWX_CONTROL = "arm_pd_ee_target_delta_pose_align2_gripper_pd_joint_pos"
URDF_VERSIONS = (
    "",  # the scripts' None: the plain robot
    "recolor_tabletop_visual_matching_1",
    "recolor_tabletop_visual_matching_2",
    "recolor_cabinet_visual_matching_1",
)
SETUPS = ("visual_matching", "variant_agg")
SUCCESS_RULES = {
    "final_step": "info['success'] of the last step; the episode runs its max steps "
    "(SimplerEnv's evaluator: it ignores the env's done flag)",
    "any_step": "success at any step; the episode ends at the first (not SimplerEnv's rule)",
}


@dataclass(frozen=True)
class Robot:
    """One robot's side of the protocol."""

    uid: str  # ManiSkill2_real2sim's robot
    family: str  # google | widowx: the action convention
    camera: str  # the observation camera SimplerEnv reads (get_image_from_maniskill2_obs_dict)
    height: int
    width: int
    control_freq: int
    sim_freq: int
    control_mode: str
    tcp_link: str  # the end-effector link of its arm controller


GOOGLE = Robot(
    "google_robot_static",
    "google",
    "overhead_camera",
    512,
    640,
    3,
    513,
    GOOGLE_CONTROL,
    "link_gripper_tcp",
)
WIDOWX = Robot(
    "widowx", "widowx", "3rd_view_camera", 480, 640, 5, 500, WIDOWX_CONTROL, "ee_gripper_link"
)
WIDOWX_SINK = Robot(
    "widowx_sink_camera_setup",
    "widowx",
    "3rd_view_camera",
    480,
    640,
    5,
    500,
    WIDOWX_CONTROL,
    "ee_gripper_link",
)


@dataclass(frozen=True)
class Episode:
    """One official episode: how the env is built (``gym.make`` kwargs beyond the robot's) and
    reset (``options``)."""

    env_id: str
    scene: str
    overlay: str | None  # file of ManiSkill2_real2sim/data/real_inpainting, or None
    build: tuple[tuple[str, Any], ...]  # extra env kwargs (urdf_version, station_name, ...)
    robot_xy: tuple[float, float]
    robot_yaw: float  # added to the base's 180 deg yaw
    obj: tuple[str, Any]  # ("init_xy", (x, y)) or ("episode_id", n)
    variant: str
    ray_tracing: bool = False  # the scripts' --enable-raytracing / shader_dir=rt

    @property
    def robot_quat(self) -> tuple[float, float, float, float]:
        return base_quat(self.robot_yaw)

    def reset_options(self) -> dict[str, Any]:
        key, value = self.obj
        return {
            "robot_init_options": {
                "init_xy": list(self.robot_xy),
                "init_rot_quat": list(self.robot_quat),
            },
            "obj_init_options": {key: list(value) if key == "init_xy" else int(value)},
        }

    def label(self) -> str:
        """What ``init_state_id`` says of the episode."""
        key, value = self.obj
        obj = f"obj_{value[0]:g}_{value[1]:g}" if key == "init_xy" else f"obj_episode_{value}"
        x, y = self.robot_xy
        return f"{self.variant}/rob_{x:g}_{y:g}_yaw_{self.robot_yaw:g}/{obj}"


@dataclass(frozen=True)
class SimplerTask:
    name: str  # SimplerEnv's task name
    robot: Robot
    max_steps: int
    instruction: str | None  # None: it depends on the episode (move near)
    setups: dict[str, list[Episode]] = field(hash=False, compare=False)


def base_quat(yaw: float) -> tuple[float, float, float, float]:
    """``(Pose(q=euler2quat(0, 0, yaw)) * Pose(q=[0, 0, 0, 1])).q`` of the scripts, (w, x, y,
    z): the robot base turned 180 deg (facing the scene) plus ``yaw``."""
    return (float(-np.sin(yaw / 2)), 0.0, 0.0, float(np.cos(yaw / 2)))


def grid(a: float, b: float, n: int) -> list[float]:
    """The scripts' ``a b n`` ranges: ``np.linspace`` with both ends."""
    return [float(v) for v in np.linspace(a, b, n)]


# -- Google robot ---------------------------------------------------------------------------------

COKE_ORIENTATIONS = {
    "horizontal": "lr_switch",
    "vertical": "laid_vertically",
    "standing": "upright",
}
COKE_XY = list(itertools.product(grid(-0.35, -0.12, 5), grid(-0.02, 0.42, 5)))
COKE_VARIANTS = (  # (variant, env id, scene, extra kwargs): rt1_pick_coke_can_variant_agg.sh
    ("base", "GraspSingleOpenedCokeCanInScene-v0", "google_pick_coke_can_1_v4", ()),
    (
        "table_texture_1",
        "GraspSingleOpenedCokeCanInScene-v0",
        "Baked_sc1_staging_objaverse_cabinet1_h870",
        (),
    ),
    (
        "table_texture_2",
        "GraspSingleOpenedCokeCanInScene-v0",
        "Baked_sc1_staging_objaverse_cabinet2_h870",
        (),
    ),
    (
        "distractors",
        "GraspSingleOpenedCokeCanDistractorInScene-v0",
        "google_pick_coke_can_1_v4",
        (),
    ),
    (
        "distractors_more",
        "GraspSingleOpenedCokeCanDistractorInScene-v0",
        "google_pick_coke_can_1_v4",
        (("distractor_config", "more"),),
    ),
    (
        "background_1",
        "GraspSingleOpenedCokeCanInScene-v0",
        "google_pick_coke_can_1_v4_alt_background",
        (),
    ),
    (
        "background_2",
        "GraspSingleOpenedCokeCanInScene-v0",
        "google_pick_coke_can_1_v4_alt_background_2",
        (),
    ),
    (
        "lighting_darker",
        "GraspSingleOpenedCokeCanInScene-v0",
        "google_pick_coke_can_1_v4",
        (("slightly_darker_lighting", True),),
    ),
    (
        "lighting_brighter",
        "GraspSingleOpenedCokeCanInScene-v0",
        "google_pick_coke_can_1_v4",
        (("slightly_brighter_lighting", True),),
    ),
)


def _coke_can(orientation: str) -> dict[str, list[Episode]]:
    flag = ((COKE_ORIENTATIONS[orientation], True),)
    vm = [
        Episode(
            "GraspSingleOpenedCokeCanInScene-v0",
            "google_pick_coke_can_1_v4",
            "google_coke_can_real_eval_1.png",
            (*flag, ("urdf_version", u)),
            (0.35, 0.20),
            0.0,
            ("init_xy", xy),
            f"urdf_{u or 'none'}",
        )
        for u in URDF_VERSIONS
        for xy in COKE_XY
    ]
    va = [
        Episode(env_id, scene, None, (*flag, *extra), (0.35, 0.20), 0.0, ("init_xy", xy), variant)
        for variant, env_id, scene, extra in COKE_VARIANTS
        for xy in COKE_XY
    ]
    return {"visual_matching": vm, "variant_agg": va}


MOVE_NEAR_VARIANTS = (  # rt1_move_near_variant_agg.sh (env MoveNearGoogleInScene-v0)
    ("base", "google_pick_coke_can_1_v4", ()),
    ("no_distractor", "google_pick_coke_can_1_v4", (("no_distractor", True),)),
    ("background_1", "google_pick_coke_can_1_v4_alt_background", ()),
    ("background_2", "google_pick_coke_can_1_v4_alt_background_2", ()),
    ("lighting_darker", "google_pick_coke_can_1_v4", (("slightly_darker_lighting", True),)),
    ("lighting_brighter", "google_pick_coke_can_1_v4", (("slightly_brighter_lighting", True),)),
    ("table_texture_1", "Baked_sc1_staging_objaverse_cabinet1_h870", ()),
    ("table_texture_2", "Baked_sc1_staging_objaverse_cabinet2_h870", ()),
)


def _move_near() -> dict[str, list[Episode]]:
    pose = ((0.35, 0.21), -0.09)
    vm = [  # the scripts' v0 (simpler_env.make's google_robot_move_near is v1)
        Episode(
            "MoveNearGoogleBakedTexInScene-v0",
            "google_pick_coke_can_1_v4",
            "google_move_near_real_eval_1.png",
            (("urdf_version", u),),
            *pose,
            ("episode_id", i),
            f"urdf_{u or 'none'}",
        )
        for u in URDF_VERSIONS
        for i in range(60)
    ]
    va = [
        Episode("MoveNearGoogleInScene-v0", scene, None, extra, *pose, ("episode_id", i), variant)
        for variant, scene, extra in MOVE_NEAR_VARIANTS
        for i in range(60)
    ]
    return {"visual_matching": vm, "variant_agg": va}


# (overlay, robot x, robot y, yaw): rt1_drawer_visual_matching.sh, configs A0 .. C2
DRAWER_CONFIGS = (
    ("open_drawer_a0.png", 0.644, -0.179, -0.03),
    ("open_drawer_a1.png", 0.765, -0.182, -0.02),
    ("open_drawer_a2.png", 0.889, -0.203, -0.06),
    ("open_drawer_b0.png", 0.652, 0.009, 0.0),
    ("open_drawer_b1.png", 0.752, 0.009, 0.0),
    ("open_drawer_b2.png", 0.851, 0.035, 0.0),
    ("open_drawer_c0.png", 0.665, 0.224, 0.0),
    ("open_drawer_c1.png", 0.765, 0.222, -0.025),
    ("open_drawer_c2.png", 0.865, 0.222, -0.025),
)
DRAWER_VM_KWARGS = (
    ("station_name", "mk_station_recolor"),
    ("light_mode", "simple"),
    ("disable_bad_material", True),
)
DRAWER_VARIANTS = (  # rt1_drawer_variant_agg.sh / rt1_put_in_drawer_variant_agg.sh: all ray traced
    ("base", "frl_apartment_stage_simple", ()),
    ("background_1", "modern_bedroom_no_roof", ()),
    ("background_2", "modern_office_no_roof", ()),
    ("lighting_brighter", "frl_apartment_stage_simple", (("light_mode", "brighter"),)),
    ("lighting_darker", "frl_apartment_stage_simple", (("light_mode", "darker"),)),
    ("cabinet_2", "frl_apartment_stage_simple", (("station_name", "mk_station2"),)),
    ("cabinet_3", "frl_apartment_stage_simple", (("station_name", "mk_station3"),)),
)


def _drawer(env_id: str) -> dict[str, list[Episode]]:
    vm = [
        Episode(
            env_id,
            "dummy_drawer",
            overlay,
            (*DRAWER_VM_KWARGS, ("urdf_version", u)),
            (x, y),
            yaw,
            ("init_xy", (0.0, 0.0)),
            f"urdf_{u or 'none'}/{overlay.removesuffix('.png')}",
            ray_tracing=True,
        )
        for u in URDF_VERSIONS
        for overlay, x, y, yaw in DRAWER_CONFIGS
    ]
    robot_xy = list(itertools.product(grid(0.65, 0.85, 3), grid(-0.2, 0.2, 3)))
    va = [
        Episode(env_id, scene, None, extra, xy, 0.0, ("init_xy", (0.0, 0.0)), variant, True)
        for variant, scene, extra in DRAWER_VARIANTS
        for xy in robot_xy
    ]
    return {"visual_matching": vm, "variant_agg": va}


APPLE_XY = list(itertools.product(grid(-0.08, -0.02, 3), grid(-0.02, 0.08, 3)))


def _apple() -> dict[str, list[Episode]]:
    env_id = "PlaceIntoClosedTopDrawerCustomInScene-v0"
    vm = [
        Episode(
            env_id,
            "dummy_drawer",
            overlay,
            (*DRAWER_VM_KWARGS, ("urdf_version", u), ("model_ids", "baked_apple_v2")),
            (x, y),
            yaw,
            ("init_xy", xy),
            f"urdf_{u or 'none'}/{overlay.removesuffix('.png')}",
            ray_tracing=True,
        )
        for u in URDF_VERSIONS
        for overlay, x, y, yaw in (DRAWER_CONFIGS[0], DRAWER_CONFIGS[3], DRAWER_CONFIGS[6])
        for xy in APPLE_XY
    ]
    va = [
        Episode(
            env_id,
            scene,
            None,
            (*extra, ("model_ids", "apple")),
            (0.65, y),
            0.0,
            ("init_xy", xy),
            variant,
            True,
        )
        for variant, scene, extra in DRAWER_VARIANTS
        for y in grid(-0.2, 0.2, 3)
        for xy in APPLE_XY
    ]
    return {"visual_matching": vm, "variant_agg": va}


# -- WidowX (Bridge): visual matching only ---------------------------------------------------------


def _bridge(env_id: str, robot: Robot) -> dict[str, list[Episode]]:
    sink = robot is WIDOWX_SINK
    scene, overlay = (
        ("bridge_table_1_v2", "bridge_sink.png")
        if sink
        else ("bridge_table_1_v1", "bridge_real_eval_1.png")
    )
    xy = (0.127, 0.06) if sink else (0.147, 0.028)
    vm = [
        Episode(env_id, scene, overlay, (), xy, 0.0, ("episode_id", i), "bridge") for i in range(24)
    ]
    return {"visual_matching": vm}


def _drawer_tasks() -> Iterator[SimplerTask]:
    for verb in ("open", "close"):
        for which in ("top", "middle", "bottom"):
            env_id = f"{verb.title()}{which.title()}DrawerCustomInScene-v0"
            yield SimplerTask(
                f"google_robot_{verb}_{which}_drawer",
                GOOGLE,
                113,
                f"{verb} {which} drawer",
                _drawer(env_id),
            )


def _build_tasks() -> dict[str, SimplerTask]:
    tasks = [
        *(
            SimplerTask(
                f"google_robot_pick_{o}_coke_can", GOOGLE, 80, "pick coke can", _coke_can(o)
            )
            for o in COKE_ORIENTATIONS
        ),
        SimplerTask("google_robot_move_near", GOOGLE, 80, None, _move_near()),
        *_drawer_tasks(),
        SimplerTask(
            "google_robot_place_apple_in_closed_top_drawer",
            GOOGLE,
            200,
            None,  # "open top drawer", then "place apple into top drawer" from step 100
            _apple(),
        ),
        SimplerTask(
            "widowx_spoon_on_towel",
            WIDOWX,
            60,
            "put the spoon on the towel",
            _bridge("PutSpoonOnTableClothInScene-v0", WIDOWX),
        ),
        SimplerTask(
            "widowx_carrot_on_plate",
            WIDOWX,
            60,
            "put carrot on plate",
            _bridge("PutCarrotOnPlateInScene-v0", WIDOWX),
        ),
        SimplerTask(
            "widowx_stack_cube",
            WIDOWX,
            60,
            "stack the green block on the yellow block",
            _bridge("StackGreenCubeOnYellowCubeBakedTexInScene-v0", WIDOWX),
        ),
        SimplerTask(
            "widowx_put_eggplant_in_basket",
            WIDOWX_SINK,
            120,
            "put eggplant into yellow basket",
            _bridge("PutEggplantInBasketScene-v0", WIDOWX_SINK),
        ),
    ]
    return {t.name: t for t in tasks}


TASKS: dict[str, SimplerTask] = _build_tasks()


def task_ids() -> list[str]:
    return [f"{name}/{setup}" for name, t in TASKS.items() for setup in t.setups]


def split_task_id(task_id: str) -> tuple[SimplerTask, str]:
    """``<task>/<setup>`` -> (the task, the setup); ValueError naming the valid ids."""
    name, _, setup = task_id.partition("/")
    task = TASKS.get(name)
    if task is None or setup not in task.setups:
        raise ValueError(f"task_id={task_id!r} is not a SIMPLER task; valid: {task_ids()}")
    return task, setup


# -- actions ---------------------------------------------------------------------------------------

ROTATIONS = ("axis_angle", "rpy")


def to_sim_action(action: np.ndarray, family: str, rotation: str, binarize: bool) -> np.ndarray:
    """A policy's 7-d action -> the one SimplerEnv's env steps with.

    Both robots take ``[dx, dy, dz, rx, ry, rz, g]``: translation in metres in the robot base
    frame, rotation as an axis-angle vector (radians, base-frame axes); neither clips the arm.
    ``rotation="rpy"``: the action's [3:6] are roll, pitch, yaw (extrinsic x, y, z: transforms3d's
    ``sxyz``, what the Bridge and fractal datasets record and what SimplerEnv's Octo and RT-1-X
    wrappers convert with ``euler2axangle``), turned into that vector. ``axis_angle``: passed on
    (SimplerEnv's RT-1 on Google). The gripper: Google's is relative (the change of the finger
    target, clipped to [-1, 1] and scaled by 1.31 rad by the controller; > 0 closes), WidowX's is
    absolute (+1 open, -1 closed; SimplerEnv's Bridge wrappers binarize it: ``binarize``)."""
    a = np.asarray(action, dtype=np.float64).copy()
    if rotation == "rpy":
        from scipy.spatial.transform import Rotation

        a[3:6] = Rotation.from_euler("xyz", a[3:6]).as_rotvec()
    elif rotation != "axis_angle":
        raise ValueError(f"rotation={rotation!r}: one of {ROTATIONS}")
    if family == "google":
        a[6] = np.clip(a[6], -1.0, 1.0)
    elif binarize:
        a[6] = 1.0 if a[6] > 0 else -1.0
    return a


# -- assets: what a task loads (paths under ManiSkill2_real2sim's data/) ---------------------------

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
