"""Data parallelism over every local JAX device, one code path for 1 or N devices.

Training and rendering are data parallel over rays: the parameters are replicated and the
rays of a batch (or of a render chunk) are split along their leading axis over a 1-D mesh
of `jax.devices()` named "rays". Inside a jitted function `shard_rays` only annotates the
layout (`jax.lax.with_sharding_constraint`); XLA's SPMD partitioner then runs each device
on its share and inserts the all-reduces that batch means and gradients need, so the
result is the single-device result up to the order of floating-point sums. On one device
the annotation changes nothing.

Several GPUs of one host are used as they are. To try the code path on a CPU, split it
into N host devices before jax starts: `XLA_FLAGS=--xla_force_host_platform_device_count=N`
(tests/test_devices.py does, in a subprocess).

Several hosts: `initialize_distributed` calls `jax.distributed.initialize` (one process per
host, process 0 runs the coordinator) before any other JAX call; `jax.devices()` then lists
the devices of every process, so the same mesh spans the hosts. Only the argument checks and
the single-process path are tested here (tests/test_devices.py); no multi-host run has been
made with this package.
"""

from __future__ import annotations

import functools
import os

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from gridnerf.errors import ConfigError


@functools.cache
def ray_mesh() -> Mesh:
    """1-D mesh of all local devices, axis "rays"."""
    return Mesh(np.asarray(jax.devices()), ("rays",))


def device_count() -> int:
    return int(ray_mesh().devices.size)


def check_divisible(n: int, field: str) -> None:
    """ConfigError unless `n` rays (or patches) split evenly over the devices."""
    d = device_count()
    if n % d:
        raise ConfigError(None, f"{field} = {n} does not split over {d} devices",
                          f"set {field} to a multiple of {d}")


def _rays_sharding(ndim: int) -> NamedSharding:
    return NamedSharding(ray_mesh(), PartitionSpec("rays", *([None] * (ndim - 1))))


def shard_rays(tree):
    """Inside jit: lay every array of `tree` out split along its leading (ray) axis."""
    if device_count() == 1:
        return tree
    return jax.tree_util.tree_map(
        lambda a: jax.lax.with_sharding_constraint(a, _rays_sharding(a.ndim)), tree)


def put_rays(*arrays):
    """Host arrays -> device arrays split along their leading axis (replicated on 1 device)."""
    if device_count() == 1:
        return arrays
    return tuple(jax.device_put(a, _rays_sharding(np.ndim(a))) for a in arrays)


def parse_coordinator(text: str) -> str:
    """`host:port` of the coordinator (process 0), checked; ConfigError otherwise."""
    host, sep, port = str(text).strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(None, f"coordinator address {text!r} is not host:port",
                          "give the address of process 0 and a free port, e.g. "
                          "--coordinator 10.0.0.1:12345")
    return f"{host}:{int(port)}"


def distributed_settings(coordinator: str | None, num_processes: int | None,
                         process_id: int | None, environ=None) -> dict | None:
    """The jax.distributed.initialize arguments of a run, or None for a single process.

    Each value comes from its argument or else from the environment variables
    JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES and JAX_PROCESS_ID. None of them set: one
    process. Some but not all, a bad address, fewer than 1 process or a process id outside
    0 .. num_processes - 1: ConfigError naming the value.
    """
    env = os.environ if environ is None else environ
    values = {"coordinator": coordinator, "num_processes": num_processes,
              "process_id": process_id}
    names = {"coordinator": ("--coordinator", "JAX_COORDINATOR_ADDRESS"),
             "num_processes": ("--num-processes", "JAX_NUM_PROCESSES"),
             "process_id": ("--process-id", "JAX_PROCESS_ID")}
    for key, (_, var) in names.items():
        if values[key] is None and env.get(var, "").strip():
            text = env[var].strip()
            if key != "coordinator":
                try:
                    text = int(text)
                except ValueError:
                    raise ConfigError(None, f"{var}={env[var]!r} is not a whole number",
                                      f"set {var} to a whole number") from None
            values[key] = text
    given = [k for k, v in values.items() if v is not None]
    if not given:
        return None
    if len(given) < 3:
        missing = " and ".join(f"{names[k][0]} (or {names[k][1]})" for k in names
                               if k not in given)
        raise ConfigError(None, f"a multi-process run needs all of --coordinator, "
                          f"--num-processes and --process-id; {missing} is missing",
                          "give all three on every process, or none for one process")
    n, i = values["num_processes"], values["process_id"]
    if n < 1:
        raise ConfigError(None, f"--num-processes = {n} is not a positive whole number",
                          "give the number of processes (hosts), >= 1")
    if not 0 <= i < n:
        raise ConfigError(None, f"--process-id = {i} is not in 0 .. {n - 1}",
                          f"number the processes 0 .. {n - 1}, process 0 on the coordinator")
    return {"coordinator_address": parse_coordinator(values["coordinator"]),
            "num_processes": n, "process_id": i}


def initialize_distributed(settings: dict | None) -> None:
    """jax.distributed.initialize(**settings) (from distributed_settings); nothing for None.

    Must run before any other JAX call of the process (jax raises otherwise). Waits for every
    process to connect (jax's initialization_timeout, 300 s by default).
    """
    if settings is None:
        return
    jax.distributed.initialize(**settings)
    ray_mesh.cache_clear()
