"""A tiny deployment (few short episodes, tiny CDT) shared by the deployment tests."""

import functools

import jax

from safecdt_jax import envs
from safecdt_jax.deploy import DeployConfig
from safecdt_jax.model import CDTConfig, init_cdt

TASK = "CarCircle2"
# 6 episodes of 80 steps, stages of 2, window 4, lambda after 2 episodes, 2 LoRA steps of 4.
# Resolved as `sweep` resolves it, so that tests which look up `_compiled(..., TINY_DEPLOY)`
# find the program the sweep ran.
TINY_DEPLOY = DeployConfig(episodes=6, horizon=80, stage_len=2, window=4, lambda_warmup=2,
                           lora_steps=2, lora_batch=4, lora_lr=3e-3).resolved()


@functools.cache
def tiny_setup():
    """(env, env params, tiny model config, base params) for the test task."""
    env, params = envs.make(TASK)
    model_cfg = CDTConfig.preset("tiny", env.observation_size, env.action_size,
                                 env.episode_length)
    base = init_cdt(jax.random.PRNGKey(0), model_cfg)
    # A biased action head: the robot drives and meets the walls, so costs and the scheduler move.
    base["action_mean"]["bias"] = jax.numpy.array([1.0, 0.5])
    return env, params, model_cfg, base
