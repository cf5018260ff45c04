"""Safety-Gymnasium's Goal and Circle tasks for the Point and Car robots, in MuJoCo-MJX.

    from safecdt_jax import envs
    env, params = envs.make("CarGoal1")
    state = env.reset(key, params)
    state = env.step(state, action, params)
"""

import contextlib
import io


def _import_mjx_quietly() -> None:
    """Imports MJX with its optional-backend probe silenced: without NVIDIA Warp installed it
    prints two 'Failed to import warp...' lines on stdout at import. Anything else it prints is
    passed through."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        from mujoco import mjx  # noqa: F401
    for line in out.getvalue().splitlines():
        if not line.startswith(("Failed to import warp:", "Failed to import mujoco_warp:")):
            print(line)


_import_mjx_quietly()

from safecdt_jax.envs.circle import CircleTask, circle_params  # noqa: E402
from safecdt_jax.envs.env import SafetyEnv  # noqa: E402
from safecdt_jax.envs.goal import GoalTask, goal_params  # noqa: E402
from safecdt_jax.envs.robots import CAR, POINT  # noqa: E402
from safecdt_jax.envs.rollout import random_episode  # noqa: E402
from safecdt_jax.envs.types import MAX_HAZARDS, MAX_VASES, EnvParams, State  # noqa: E402

# Per robot: bump when that robot's dynamics or sensors change (models, traction, sensor
# models). Cached data and expert snapshots made under another version are rebuilt. Car 3: the
# caster's slip and the chassis chatter (sim2sim); Car 4: contact forces with friction limits
# (turning on one wheel, mixed drive); Car 5: the chassis roll reaches the velocimeter's x
# (sim2sim: its std was a quarter of the native one); Car 6: contact forces bend smoothly onto
# their friction limits and the traction constants are refitted (native speed-up and switching);
# Car 7: the caster ball stick-slips above 6 rad/s (experts had read its steady roll as an
# odometer).
PHYSICS_VERSIONS = {"Car": 7, "Point": 2}
# Per task: bump when a task's rules change (rewards, costs, objects). Goal 2: vases are knocked
# ahead and creep to rest, and cost as in Safety-Gymnasium (2026-12-06; level 1's costs are
# unchanged, so level-1 data and experts stay valid). Goal 3: the push constants per robot
# (the Car's vase parts sooner, e 1.5 and creep 2 steps; the Point's e 1.0), fitted to native
# per-term cost steps (2026-12-07; level 1's costs are again unchanged).
TASK_VERSIONS = {"Goal": 3, "Circle": 1}

NAMES = tuple(f"{robot}{task}{level}" for robot in ("Car", "Point") for task in ("Goal", "Circle")
              for level in (1, 2))

_ENVS: dict[str, SafetyEnv] = {}


def _robot_name(name: str) -> str:
    """'Car' or 'Point' for a valid task name; ValueError naming the valid names otherwise."""
    if name not in NAMES:
        raise ValueError(f"unknown task {name!r}; valid names: {', '.join(NAMES)}")
    return "Car" if name.startswith("Car") else "Point"


def physics_version(name: str) -> int:
    """The physics version of task `name`'s robot (`PHYSICS_VERSIONS`); ValueError if unknown."""
    return PHYSICS_VERSIONS[_robot_name(name)]


def env_version(name: str) -> str:
    """What identifies the dynamics and rules of task `name`, e.g. 'Car5-Goal2': its robot's
    physics version and its task's rules version. ValueError if the name is unknown."""
    robot = _robot_name(name)
    task = name[len(robot):-1]
    return f"{robot}{PHYSICS_VERSIONS[robot]}-{task}{TASK_VERSIONS[task]}"


def make(name: str) -> tuple[SafetyEnv, EnvParams]:
    """The env and default params for a task name such as 'CarGoal2' (robot, task, level).

    Both levels of a task return the same env object, so they share compiled code.
    Raises ValueError naming the valid names for an unknown name.
    """
    robot_name, level = _robot_name(name), int(name[-1])
    task_name = name[len(robot_name):-1]
    key = robot_name + task_name
    if key not in _ENVS:
        robot = CAR if robot_name == "Car" else POINT
        task = GoalTask() if task_name == "Goal" else CircleTask()
        _ENVS[key] = SafetyEnv(name=key, robot=robot, task=task)
    params = goal_params(level) if task_name == "Goal" else circle_params(level)
    return _ENVS[key], params


__all__ = ["MAX_HAZARDS", "MAX_VASES", "NAMES", "PHYSICS_VERSIONS", "TASK_VERSIONS", "EnvParams",
           "SafetyEnv",
           "State", "env_version", "make", "physics_version", "random_episode"]
