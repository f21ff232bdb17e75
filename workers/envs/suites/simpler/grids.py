"""SIMPLER's official tasks and their episode lists, as the evaluation scripts enumerate them.

Read off SimplerEnv's ``scripts/rt1_*.sh`` and ``scripts/octo_bridge.sh`` (SimplerEnv 4ab7178);
the types they are made of (robots, episodes) are ``protocol``'s.

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

from workers.envs.suites.simpler.protocol import (
    GOOGLE,
    WIDOWX,
    WIDOWX_SINK,
    Episode,
    Robot,
    SimplerTask,
    grid,
)

URDF_VERSIONS = (
    "",  # the scripts' None: the plain robot
    "recolor_tabletop_visual_matching_1",
    "recolor_tabletop_visual_matching_2",
    "recolor_cabinet_visual_matching_1",
)

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


def episodes_of(task_id: str) -> list[Episode]:
    """The official episode list of ``<task>/<setup>``; ValueError naming the valid ids."""
    task, setup = split_task_id(task_id)
    return task.setups[setup]
