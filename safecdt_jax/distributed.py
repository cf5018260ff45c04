"""Several cooperating processes, through JAX's own multi-controller runtime.

N copies of the same command, started with the same coordinator address and process count and
each with its own process id (`jax.distributed.initialize`), see one global list of devices:
a sweep shards its seeds over all of them (`deploy.sweep`), pretraining its batch
(`pretrain.loop`), every process computes its shard, and the results are gathered to every
process; process 0 alone writes them (`is_writer`). One process, the default, never touches
this runtime, so its results are the same bits as before.

The settings come from command-line flags or JAX's usual environment variables
(`JAX_COORDINATOR_ADDRESS`, `JAX_NUM_PROCESSES`, `JAX_PROCESS_ID`; `JAX_LOCAL_DEVICE_IDS`
picks each process's GPUs, read by JAX itself). Every process must load the same inputs
(checkpoint, data set): the folders are assumed shared, as on one machine or a shared disk.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

import jax
import numpy as np

ENV_VARS = ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID")
# How long a process waits for its peers to join (s): long enough for N interpreters to import
# JAX on a loaded machine, short enough that a missing peer fails the run the same minute.
JOIN_TIMEOUT_S = 120
# How long the other processes wait while process 0 alone prepares something (source data,
# a pretrained checkpoint, baselines): hours on a CPU.
PREPARE_TIMEOUT_S = 6 * 3600
T = TypeVar("T")


@dataclass(frozen=True)
class Cluster:
    """Where this process stands among the cooperating ones.

    Attributes:
        coordinator: `host:port` of process 0's coordination service (None with one process).
        num_processes: how many processes cooperate (1: the default, no runtime started).
        process_id: this process's rank, 0 <= process_id < num_processes; 0 writes results.
    """

    coordinator: str | None = None
    num_processes: int = 1
    process_id: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.num_processes, bool) or not isinstance(self.num_processes, int) \
                or self.num_processes < 1:
            raise ValueError(f"the number of processes must be a positive integer, got "
                             f"{self.num_processes!r}")
        if isinstance(self.process_id, bool) or not isinstance(self.process_id, int) \
                or not 0 <= self.process_id < self.num_processes:
            raise ValueError(f"process id {self.process_id!r} out of range for "
                             f"{self.num_processes} process(es): it must be in "
                             f"0..{self.num_processes - 1}")
        if self.num_processes > 1 and not re.fullmatch(r"\S+:\d+", self.coordinator or ""):
            raise ValueError(f"{self.num_processes} processes need a coordinator address "
                             f"HOST:PORT (--coordinator or JAX_COORDINATOR_ADDRESS), got "
                             f"{self.coordinator!r}")


def _env_int(environ: Mapping[str, str], name: str) -> int | None:
    text = environ.get(name)
    if text is None or text == "":
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {text!r}") from None


def cluster_from(coordinator: str | None = None, num_processes: int | None = None,
                 process_id: int | None = None,
                 environ: Mapping[str, str] = os.environ) -> Cluster:
    """The `Cluster` of explicit settings, each unset one read from its environment variable
    (`ENV_VARS`); with none set anywhere, one process. ValueError on an inconsistent set."""
    coordinator = coordinator or environ.get(ENV_VARS[0]) or None
    num_processes = num_processes if num_processes is not None else _env_int(environ,
                                                                             ENV_VARS[1])
    process_id = process_id if process_id is not None else _env_int(environ, ENV_VARS[2])
    if num_processes is None:
        if process_id not in (None, 0):
            raise ValueError(f"process id {process_id} given without the number of processes "
                             f"(--num-processes or JAX_NUM_PROCESSES)")
        return Cluster(coordinator, 1, 0)
    if num_processes > 1 and process_id is None:
        raise ValueError(f"{num_processes} processes need this process's id (--process-id or "
                         f"JAX_PROCESS_ID)")
    return Cluster(coordinator, num_processes, process_id or 0)


def initialize(cluster: Cluster) -> bool:
    """Join the cooperating processes of `cluster` (`jax.distributed.initialize`); call it
    before any JAX computation. One process: nothing happens. Returns whether the runtime is
    on. On CPU the cross-process collectives go through gloo (TCP)."""
    if cluster.num_processes == 1:
        return False
    if jax.distributed.is_initialized():
        if (jax.process_count(), jax.process_index()) != (cluster.num_processes,
                                                          cluster.process_id):
            raise ValueError("the distributed runtime is already on with other settings")
        return True
    # gloo is jax 0.10's default already; named so that a changed default cannot leave CPU
    # processes without cross-process collectives.
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=cluster.coordinator,
                               num_processes=cluster.num_processes,
                               process_id=cluster.process_id,
                               initialization_timeout=JOIN_TIMEOUT_S)
    return True


def is_writer() -> bool:
    """True in the process that writes results: process 0 (the only one when alone)."""
    return jax.process_index() == 0


def spans_processes(devices: list) -> bool:
    """True when `devices` include another process's (a global mesh over several)."""
    return any(d.process_index != jax.process_index() for d in devices)


def to_global(tree: Any, sharding: jax.sharding.Sharding) -> Any:
    """Every leaf of `tree` (the same value in every process) as a global array laid out by
    `sharding`; each process places only the slices its own devices hold. No cross-process
    check of the values (which `jax.device_put` would make, one collective per leaf)."""
    def put(leaf):
        if isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype,
                                                                  jax.dtypes.prng_key):
            return jax.random.wrap_key_data(put(jax.random.key_data(leaf)),
                                            impl=jax.random.key_impl(leaf))
        host = np.asarray(jax.device_get(leaf))
        return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])

    return jax.tree.map(put, tree)


def gather(tree: Any) -> Any:
    """Every leaf of `tree` as a NumPy array holding the whole global value, in every process
    (a leaf that is already whole in this process is only copied to the host)."""
    from jax.experimental import multihost_utils

    def fetch(leaf):
        if isinstance(leaf, jax.Array) and not leaf.is_fully_addressable:
            return np.asarray(multihost_utils.process_allgather(leaf, tiled=True))
        return np.asarray(jax.device_get(leaf))

    return jax.tree.map(fetch, tree)


def barrier(name: str, timeout_s: float = PREPARE_TIMEOUT_S) -> None:
    """Wait until every process reaches the barrier `name` (at most `timeout_s`); nothing with
    one process. Uses the coordination service, not a device collective, so a long wait (the
    other processes idle while process 0 pretrains) runs into no collective timeout."""
    if jax.process_count() == 1:
        return
    from jax._src import distributed as _distributed  # the runtime's client has the barrier

    _distributed.global_state.client.wait_at_barrier(name, int(timeout_s * 1000))


def process_zero_first(name: str, make: Callable[[], T]) -> T:
    """`make()` in process 0 alone, then, once it has finished (barrier `name`), in the other
    processes, which find what it made on the shared disk (cached data, a checkpoint) instead
    of making it again at the same time. One process: just `make()`."""
    if jax.process_count() == 1:
        return make()
    made = make() if is_writer() else None
    barrier(name)
    return made if is_writer() else make()


def local_copy(tree: Any) -> Any:
    """Every leaf of `tree` replicated over several devices as this process's own
    single-device copy: what a checkpoint writer saves alone, and what a one-device process
    restores later. Single-device leaves are unchanged."""
    def local(leaf):
        if isinstance(leaf, jax.Array) and len(leaf.sharding.device_set) > 1:
            return leaf.addressable_data(0)
        return leaf

    return jax.tree.map(local, tree)
