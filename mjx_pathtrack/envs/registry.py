"""The environments of a training configuration by task name, all made the same way:
``make(config, split, root)`` (``config``: a :class:`~mjx_pathtrack.config.run.TrainConfig`).

To add a task: write its environment in :mod:`mjx_pathtrack.envs.tasks` with a factory of this
signature, its ``TaskConfig`` and ``PRESET``, and register the factory in :data:`FACTORIES`
(docs/extending.md).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from mjx_pathtrack.core.knot_rule import KnotRule
from mjx_pathtrack.envs.executors import MjxExecutor
from mjx_pathtrack.envs.tracking import PathTrackingEnv

#: executors of the plain tracking task (``TrainConfig.executor``)
EXECUTORS = ("kinematic", "mjx")


def make_tracking(config, split: str = "train", root=None) -> PathTrackingEnv:
    """Path tracking over one dataset split of a registry robot (``executor`` kinematic or MJX)."""
    from mjx_pathtrack.paths import datasets
    from mjx_pathtrack.robots import registry as robots

    root = config.dataset_root if root is None else root
    robot = robots.load_robot(config.robot, dt=config.env.dt)
    meta = datasets.read_config(config.robot, config.dataset, root)
    paths = datasets.load_paths(config.robot, config.dataset, split, root=root)
    return tracking_env(robot, paths, float(meta["max_dis_between_knots"]), config.env_config(), config.executor,
                        KnotRule.of_dataset(meta))


def tracking_env(robot, paths, max_dis: float, env_config, executor: str = "kinematic",
                 knot_rule: KnotRule | None = None) -> PathTrackingEnv:
    """Path tracking of a registry ``robot`` over ``paths`` (a stacked ``Path``) whose knots are
    at most ``max_dis`` [rad] apart, with ``env_config`` and the ``executor`` (:data:`EXECUTORS`);
    ``knot_rule``: the training paths' (default: the papers' curvature rule capped at ``max_dis``)."""
    if executor not in EXECUTORS:
        raise ValueError(f"unknown executor {executor!r}; known: {', '.join(EXECUTORS)}")
    return PathTrackingEnv(robot.limits, paths, max_dis, env_config, path_joints=np.flatnonzero(np.asarray(robot.path_mask)),
                           home=robot.q0, executor=MjxExecutor(robot) if executor == "mjx" else None,
                           knot_rule=knot_rule)


def _ball_on_plate(config, split: str = "train", root=None):
    from mjx_pathtrack.envs.tasks import ball_on_plate

    return ball_on_plate.make_task_env(config, split, root)


def _balance(config, split: str = "train", root=None):
    from mjx_pathtrack.envs.tasks import humanoid_balance

    return humanoid_balance.make_env(config, split, root=root)


#: task name -> ``factory(config, split, root) -> env`` (``TrainConfig.task``)
FACTORIES: dict[str, Callable] = {"tracking": make_tracking, "ball_on_plate": _ball_on_plate, "balance": _balance}


def make(config, split: str = "train", root=None) -> PathTrackingEnv:
    """The environment of ``config.task`` over the dataset split ``split`` (``train`` or ``test``;
    dataset under ``root``, default ``config.dataset_root``); the training split's episodes end
    at ``env.train_terminate_deviation`` where it is set."""
    if config.task not in FACTORIES:
        raise ValueError(f"unknown task {config.task!r}; known: {', '.join(FACTORIES)}")
    tube = config.env.train_terminate_deviation
    if split == "train" and tube is not None:   # training episodes end in a tighter tube than the bar
        config = config.replace(terminate_deviation=tube)
    return FACTORIES[config.task](config, split, root)
