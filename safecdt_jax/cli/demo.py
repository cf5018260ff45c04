"""`safecdt-jax analyze envs`: a random policy in every task (return, cost, env steps/s)."""

import time

import typer

from safecdt_jax.cli.app import analyze, fail


@analyze.command("envs")
def demo(
    tasks: str = typer.Option("all", help="Comma-separated task names, or 'all'."),
    episodes: int = typer.Option(16, min=1, help="Random-policy episodes per task (one batch)."),
    seed: int = typer.Option(0, help="PRNG seed."),
) -> None:
    """Rolls out the uniform random policy in every task; prints return, cost and env steps/s."""
    import jax
    from tqdm import tqdm

    from safecdt_jax import envs
    from safecdt_jax.envs.rollout import run_episode

    names = envs.NAMES if tasks == "all" else tuple(t.strip() for t in tasks.split(","))
    for name in names:
        if name not in envs.NAMES:
            fail(f"unknown task {name!r}; valid: {', '.join(envs.NAMES)}")
    rows = []
    for name in tqdm(names, desc="tasks", unit="task"):
        env, params = envs.make(name)
        fn = jax.jit(jax.vmap(lambda k, env=env, params=params: run_episode(env, params, k)))
        keys = jax.random.split(jax.random.PRNGKey(seed), episodes)
        jax.block_until_ready(fn(keys))  # compile
        start = time.perf_counter()
        out = jax.block_until_ready(fn(keys))
        secs = time.perf_counter() - start
        rows.append((name, float(out["return"].mean()), float(out["cost"].mean()),
                     episodes * env.episode_length / secs))
    typer.echo(f"\nuniform random policy, {episodes} episodes per task "
               f"({jax.devices()[0].platform})")
    typer.echo(f"{'task':14s}{'return':>10s}{'cost':>10s}{'env steps/s':>14s}")
    for name, ret, cost, sps in rows:
        typer.echo(f"{name:14s}{ret:10.2f}{cost:10.1f}{sps:14,.0f}")
