"""Safety-Gymnasium's Goal and Circle tasks for the Point and Car robots, in MuJoCo-MJX.

    env, params = envs.make("CarGoal1")
    state = env.reset(key, params)
    state = env.step(state, action, params)
"""

from envs.circle import CircleTask, circle_params
from envs.env import SafetyEnv
from envs.goal import GoalTask, goal_params
from envs.robots import CAR, POINT
from envs.rollout import random_episode
from envs.types import MAX_HAZARDS, MAX_VASES, EnvParams, State

# Bump whenever the dynamics or the task rules change (robot models, traction, costs, layouts):
# cached data sets collected under another version are collected again.
PHYSICS_VERSION = 2

NAMES = tuple(f"{robot}{task}{level}" for robot in ("Car", "Point") for task in ("Goal", "Circle")
              for level in (1, 2))

_ENVS: dict[str, SafetyEnv] = {}


def make(name: str) -> tuple[SafetyEnv, EnvParams]:
    """The env and default params for a task name such as 'CarGoal2' (robot, task, level).

    Both levels of a task return the same env object, so they share compiled code.
    Raises ValueError naming the valid names for an unknown name.
    """
    if name not in NAMES:
        raise ValueError(f"unknown task {name!r}; valid names: {', '.join(NAMES)}")
    robot_name, level = ("Car" if name.startswith("Car") else "Point"), int(name[-1])
    task_name = name[len(robot_name):-1]
    key = robot_name + task_name
    if key not in _ENVS:
        robot = CAR if robot_name == "Car" else POINT
        task = GoalTask() if task_name == "Goal" else CircleTask()
        _ENVS[key] = SafetyEnv(name=key, robot=robot, task=task)
    params = goal_params(level) if task_name == "Goal" else circle_params(level)
    return _ENVS[key], params


__all__ = ["MAX_HAZARDS", "MAX_VASES", "NAMES", "PHYSICS_VERSION", "EnvParams", "SafetyEnv",
           "State", "make", "random_episode"]
