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
"""

from __future__ import annotations

import functools

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
