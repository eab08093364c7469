"""Atomic, finite-only checkpoints of pytrees of arrays.

A checkpoint is one `.npz` holding named arrays plus a JSON header. It is
written to `<name>.tmp` and moved into place with `os.replace`, so a crash
never leaves a half-written file that looks valid. Non-finite arrays are
refused (`NumericsError`): no NaN or Inf ever reaches a checkpoint.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import jax
import numpy as np

from gridnerf.errors import NumericsError


def atomic_write_bytes(path: Path, data: bytes) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def flatten(tree) -> list[np.ndarray]:
    """Leaves of a pytree as host numpy arrays, in jax's canonical order."""
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]


def unflatten_like(template, leaves: list[np.ndarray]):
    """Put saved `leaves` into the structure of `template`, checking shapes."""
    tmpl_leaves, treedef = jax.tree_util.tree_flatten(template)
    if len(tmpl_leaves) != len(leaves):
        raise ValueError(f"checkpoint has {len(leaves)} arrays, expected {len(tmpl_leaves)}")
    for a, b in zip(tmpl_leaves, leaves, strict=True):
        if np.shape(a) != np.shape(b):
            raise ValueError(f"checkpoint array shape {np.shape(b)} != expected {np.shape(a)}")
    return jax.tree_util.tree_unflatten(treedef, [np.asarray(x) for x in leaves])


def save(path: Path, groups: dict[str, list[np.ndarray]], header: dict) -> None:
    """Write `groups` (name -> list of arrays) and a JSON `header` atomically to `path`."""
    arrays = {}
    for name, leaves in groups.items():
        for i, leaf in enumerate(leaves):
            leaf = np.asarray(leaf)
            if np.issubdtype(leaf.dtype, np.floating) and not np.all(np.isfinite(leaf)):
                raise NumericsError(
                    path,
                    f"refusing to checkpoint non-finite values in {name}[{i}]",
                    "lower the learning rates or check the input frames for NaN; "
                    "training resumes from the last good checkpoint",
                )
            arrays[f"{name}/{i:04d}"] = leaf
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def load(path: Path) -> tuple[dict[str, list[np.ndarray]], dict]:
    """Read a checkpoint written by `save`: (groups, header)."""
    with np.load(Path(path)) as z:
        header = json.loads(bytes(z["header"]).decode())
        groups: dict[str, list[np.ndarray]] = {}
        for key in sorted(k for k in z.files if k != "header"):
            name, _ = key.rsplit("/", 1)
            groups.setdefault(name, []).append(z[key])
    return groups, header
