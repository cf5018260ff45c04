"""The peer side of the benchmark: runs inside a peer virtualenv, one JSON request per stdin line.

Started by `benchmarks.run_all` with a peer environment's interpreter (`benchmarks/peers/setup.py`)
and kept alive, so that its environments and models are built once and the two sides can be timed
alternately (A B A B). It imports only the peers' packages, never this project. Each request is
`{"cmd": name, **arguments}`; each answer is one JSON line `{"ok": true, ...}` or
`{"ok": false, "error": text}` on the original stdout (everything the libraries print goes to
stderr instead, so it cannot corrupt the protocol).

Commands: `versions`, `env_steps` (Safety-Gymnasium), `train`, `infer`, `flops`, `gemm` (OSRL's
CDT in PyTorch), `deploy` (OSRL's own `CDTTrainer.evaluate` over Safety-Gymnasium),
`baseline_train` (OSRL's BCQL, BEARL and CPQ).
"""

import dataclasses
import importlib.metadata
import importlib.util
import json
import os
import platform
import sys
import time

import numpy as np

THREADS = int(os.environ.get("BENCH_THREADS", "1"))
_CACHE: dict = {}


def _allow_ndarray_dataclass_defaults() -> None:
    """Lets Safety-Gymnasium 1.0.0 import on Python 3.11 without touching its files.

    Its config dataclasses have numpy-array defaults, which Python 3.11 rejects as mutable. Each
    such default becomes a factory returning a copy (per-instance arrays instead of one shared
    array; the values are the same).
    """
    if sys.version_info < (3, 11) or getattr(dataclasses, "_peer_patched", False):
        return
    original = dataclasses._get_field

    def get_field(cls, name, a_type, *rest):
        default = cls.__dict__.get(name)
        if isinstance(default, np.ndarray):
            setattr(cls, name, dataclasses.field(default_factory=default.copy))
        return original(cls, name, a_type, *rest)

    dataclasses._get_field = get_field
    dataclasses._peer_patched = True


def versions() -> dict:
    """Interpreter, packages and thread count of this environment."""
    out = {"python": platform.python_version(), "threads": THREADS}
    for dist in ("numpy", "torch", "mujoco", "gymnasium", "safety-gymnasium", "osrl-lib"):
        try:
            out[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            pass
    return out


def _safety_gym():
    _allow_ndarray_dataclass_defaults()
    import safety_gymnasium

    return safety_gymnasium


def env_steps(task: str, n_envs: int, steps: int) -> dict:
    """Seconds of `steps` random-action steps of one env (`n_envs` 0) or a sync vector env.

    Calls continue the same env, and `steps` is the episode length, so every call contains
    exactly one reset per env (the time-limit truncation of the previous episode): resets are
    included, as on our side.
    """
    sg = _safety_gym()
    key = ("env", task, n_envs)
    if key not in _CACHE:
        env_id = f"Safety{task}-v0"
        # Sync: every env on this process's one core (the async one forks n processes).
        env = (sg.make(env_id) if n_envs == 0
               else sg.vector.make(env_id, num_envs=n_envs, asynchronous=False))
        env.reset(seed=0)
        _CACHE[key] = (env, np.random.default_rng(0))
    env, rng = _CACHE[key]
    shape = (steps, *env.action_space.shape)
    actions = rng.uniform(-1.0, 1.0, shape)
    t = time.perf_counter()
    for a in actions:
        _, _, _, terminated, truncated, _ = env.step(a)
        if n_envs == 0 and (terminated or truncated):
            env.reset()
    seconds = time.perf_counter() - t
    return {"seconds": seconds, "env_steps": steps * max(n_envs, 1)}


def _cdt(obs_dim: int, act_dim: int, episode_len: int):
    """OSRL's CDT and CDTTrainer with the settings of its Safety-Gymnasium config (`osrl` size)."""
    key = ("cdt", obs_dim, act_dim, episode_len)
    if key not in _CACHE:
        import torch
        from osrl.algorithms.cdt import CDT, CDTTrainer

        torch.manual_seed(0)
        model = CDT(state_dim=obs_dim, action_dim=act_dim, max_action=1.0, seq_len=10,
                    episode_len=episode_len, embedding_dim=128, num_layers=3, num_heads=8,
                    attention_dropout=0.1, residual_dropout=0.1, embedding_dropout=0.1,
                    time_emb=True, use_rew=True, use_cost=True, cost_transform=True,
                    stochastic=True, init_temperature=0.1, target_entropy=-act_dim)
        trainer = CDTTrainer(model, env=None, learning_rate=1e-4, weight_decay=1e-4,
                             betas=(0.9, 0.999), clip_grad=0.25, lr_warmup_steps=500,
                             reward_scale=0.1, cost_scale=1.0, loss_cost_weight=0.02,
                             loss_state_weight=0.0, cost_reverse=False, no_entropy=False,
                             device="cpu")
        _CACHE[key] = (model, trainer)
    return _CACHE[key]


def _window(batch: int, obs_dim: int, act_dim: int, k: int = 10) -> list:
    """A synthetic batch in the order of OSRL's `SequenceDataset` samples."""
    import torch

    g = torch.Generator().manual_seed(batch)
    return [torch.randn(batch, k, obs_dim, generator=g),
            torch.rand(batch, k, act_dim, generator=g) * 2 - 1,
            torch.rand(batch, k, generator=g) * 4,
            torch.rand(batch, k, generator=g) * 60,
            torch.arange(100, 100 + k).repeat(batch, 1),
            torch.ones(batch, k),
            torch.full((batch,), 30.0),
            (torch.rand(batch, k, generator=g) < 0.03).float()]


def train(batch: int, steps: int, obs_dim: int, act_dim: int, episode_len: int) -> dict:
    """Seconds of `steps` calls of OSRL's `CDTTrainer.train_one_step` on a fixed batch.

    Window sampling (OSRL's DataLoader) is not included: on our side it is (on the device).
    """
    model, trainer = _cdt(obs_dim, act_dim, episode_len)
    model.train()
    data = _window(batch, obs_dim, act_dim)
    t = time.perf_counter()
    for _ in range(steps):
        trainer.train_one_step(*data)
    return {"seconds": time.perf_counter() - t, "steps": steps,
            "params": sum(p.numel() for p in model.parameters())}


def _baseline(algo: str, obs_dim: int, act_dim: int, episode_len: int):
    """OSRL's BCQL, BEARL or CPQ with the networks and rates of its Safety-Gymnasium configs."""
    key = (algo, obs_dim, act_dim, episode_len)
    if key not in _CACHE:
        import torch
        from osrl.algorithms import BCQL, BEARL, CPQ, BCQLTrainer, BEARLTrainer, CPQTrainer

        torch.manual_seed(0)
        common = dict(state_dim=obs_dim, action_dim=act_dim, max_action=1.0,
                      a_hidden_sizes=[256, 256], c_hidden_sizes=[256, 256],
                      vae_hidden_sizes=400, sample_action_num=10, gamma=0.99, tau=0.005,
                      num_q=2, num_qc=2, cost_limit=30, episode_len=episode_len, device="cpu")
        if algo == "bcql":
            model = BCQL(**common, phi=0.05, lmbda=0.75, beta=0.5, PID=[0.1, 0.003, 0.001])
            trainer = BCQLTrainer(model, None, actor_lr=1e-3, critic_lr=1e-3, vae_lr=1e-3,
                                  reward_scale=0.1, cost_scale=1.0, device="cpu")
        elif algo == "bearl":
            model = BEARL(**common, beta=0.5, lmbda=0.75, mmd_sigma=50, target_mmd_thresh=0.05,
                          num_samples_mmd_match=10, PID=[0.1, 0.003, 0.001],
                          kernel="gaussian", start_update_policy_step=0)
            trainer = BEARLTrainer(model, None, actor_lr=1e-3, critic_lr=1e-3, alpha_lr=1e-3,
                                   vae_lr=1e-3, reward_scale=0.1, cost_scale=1.0, device="cpu")
        else:
            common.update(num_q=2, num_qc=2)
            model = CPQ(**common, beta=0.5, qc_scalar=1.5)
            trainer = CPQTrainer(model, None, actor_lr=1e-4, critic_lr=1e-3, alpha_lr=1e-4,
                                 vae_lr=1e-3, reward_scale=0.1, cost_scale=1.0, device="cpu")
        _CACHE[key] = (model, trainer)
    return _CACHE[key]


def baseline_train(algo: str, batch: int, steps: int, obs_dim: int, act_dim: int,
                   episode_len: int) -> dict:
    """Seconds of `steps` calls of OSRL's `train_one_step` of `algo` on a fixed random batch of
    transitions (sampling them is not included; on our side it is, inside the scan)."""
    import torch

    model, trainer = _baseline(algo, obs_dim, act_dim, episode_len)
    g = torch.Generator().manual_seed(batch)
    data = [torch.randn(batch, obs_dim, generator=g), torch.randn(batch, obs_dim, generator=g),
            torch.rand(batch, act_dim, generator=g) * 2 - 1,
            torch.rand(batch, generator=g) * 0.1,
            (torch.rand(batch, generator=g) < 0.05).float(), torch.zeros(batch)]
    t = time.perf_counter()
    for _ in range(steps):
        trainer.train_one_step(*data)
    return {"seconds": time.perf_counter() - t, "steps": steps,
            "params": sum(p.numel() for p in model.parameters())}


def infer(batch: int, calls: int, obs_dim: int, act_dim: int, episode_len: int) -> dict:
    """Seconds of `calls` evaluation forwards on a full 10-step window, as OSRL's rollout does.

    Same work per call as one step of `CDTTrainer.rollout`: forward without autograd, Gaussian
    mean, clamp, newest action to numpy.
    """
    import torch

    model, _ = _cdt(obs_dim, act_dim, episode_len)
    model.eval()
    s, a, r, c, ts, _, epi_cost, _ = _window(batch, obs_dim, act_dim)
    t = time.perf_counter()
    with torch.no_grad():
        for _ in range(calls):
            acts, _, _ = model(s, a, r, c, ts, None, epi_cost)
            acts.mean.clamp(-1.0, 1.0)[:, -1].cpu().numpy()
    model.train()
    return {"seconds": time.perf_counter() - t, "calls": calls}


def flops(obs_dim: int, act_dim: int, episode_len: int, context: int) -> dict:
    """Matmul FLOPs of one batch-1 evaluation forward with `context` steps (torch's counter)."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    model, _ = _cdt(obs_dim, act_dim, episode_len)
    model.eval()
    s, a, r, c, ts, _, epi_cost, _ = _window(1, obs_dim, act_dim, context)
    counter = FlopCounterMode(display=False)
    with torch.no_grad(), counter:
        model(s, a, r, c, ts, None, epi_cost)
    model.train()
    return {"flops": counter.get_total_flops()}


def gemm(n: int, calls: int) -> dict:
    """Seconds of `calls` float32 n x n matrix products in PyTorch (this CPU's matmul rate)."""
    import torch

    x = torch.randn(n, n)
    torch.mm(x, x)
    t = time.perf_counter()
    for _ in range(calls):
        torch.mm(x, x)
    return {"seconds": time.perf_counter() - t, "flops": 2.0 * n**3 * calls}


def _timed(env):
    """`env` wrapped so that the seconds spent in its `step` and `reset` add up in `.seconds`."""
    import gymnasium

    class Timed(gymnasium.Wrapper):
        seconds = 0.0

        def step(self, action):
            t = time.perf_counter()
            out = self.env.step(action)
            self.seconds += time.perf_counter() - t
            return out

        def reset(self, **kwargs):
            t = time.perf_counter()
            out = self.env.reset(**kwargs)
            self.seconds += time.perf_counter() - t
            return out

    return Timed(env)


def deploy(task: str, seeds: int, episodes: int, target_return: float, target_cost: float,
           obs_dim: int, act_dim: int, episode_len: int) -> dict:
    """OSRL's evaluation the way its scripts run it: seed after seed, episode after episode.

    The env is Safety-Gymnasium's gymnasium-API task (`Safety<Task>Gymnasium-v0`, cost in
    `info["cost"]`, what DSRL's offline env wraps) with rewards scaled by 0.1 (DSRL's
    `wrap_env`); `CDTTrainer.evaluate` runs the episodes. Returns the wall seconds and the part
    spent inside the env.
    """
    import gymnasium
    import torch

    _safety_gym()
    key = ("deploy", task)
    if key not in _CACHE:
        env = gymnasium.make(f"Safety{task}Gymnasium-v0")
        env = gymnasium.wrappers.TransformReward(env, lambda r: 0.1 * r)
        _CACHE[key] = _timed(env)
    env = _CACHE[key]
    _, trainer = _cdt(obs_dim, act_dim, episode_len)
    trainer.env = env
    env.seconds = 0.0
    rets, costs, steps = [], [], 0
    t = time.perf_counter()
    for seed in range(seeds):
        torch.manual_seed(seed)
        env.reset(seed=seed)
        ret, cost, length = trainer.evaluate(episodes, target_return * 0.1, target_cost)
        rets.append(float(ret))
        costs.append(float(cost))
        steps += int(length * episodes)
    return {"seconds": time.perf_counter() - t, "env_seconds": env.seconds, "env_steps": steps,
            "episodes": seeds * episodes, "mean_return": float(np.mean(rets)),
            "mean_cost": float(np.mean(costs))}


COMMANDS = {f.__name__: f for f in (versions, env_steps, train, infer, flops, gemm, deploy,
                                     baseline_train)}


def main() -> None:
    """Serves requests until stdin closes."""
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # library prints (and C-level writes) go to stderr from now on
    if importlib.util.find_spec("torch"):
        import torch

        torch.set_num_threads(THREADS)
    for line in sys.stdin:
        request = json.loads(line)
        wall, cpu = time.perf_counter(), time.process_time()
        try:
            result = {"ok": True, **COMMANDS[request.pop("cmd")](**request)}
        except Exception as e:  # reported to the caller, which decides what to do
            result = {"ok": False, "error": f"{type(e).__name__}: {e}"}
        # CPU seconds of all this process's threads per wall second: ~1.0 = one busy thread.
        result["cpu_per_wall"] = (time.process_time() - cpu) / (time.perf_counter() - wall)
        answers.write(json.dumps(result) + "\n")
        answers.flush()


if __name__ == "__main__":
    main()
