"""Atomic, finite-only checkpoints of pytrees of arrays.

A checkpoint is one `.npz` holding named arrays plus a JSON header. It is
written to `<name>.tmp` and moved into place with `os.replace`, so a crash
never leaves a half-written file that looks valid; a failed write (disk full)
removes the `.tmp` and raises `WriteError` (gridnerf.atomic). Non-finite arrays are
refused (`NumericsError`): no NaN or Inf ever reaches a checkpoint. A file
that cannot be read back raises `CheckpointError` naming it and the fix.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from gridnerf import atomic
from gridnerf.errors import CheckpointError, NumericsError


def _atomic_write(path: Path, write: Callable) -> None:
    """gridnerf.atomic.write with `write(file object)` (WriteError on disk full)."""

    def fill(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            write(f)

    atomic.write(path, fill)


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
    _atomic_write(Path(path), lambda f: np.savez(f, **arrays))


def load(path: Path) -> tuple[dict[str, list[np.ndarray]], dict]:
    """Read a checkpoint written by `save`: (groups, header). CheckpointError naming the
    file if it is missing, truncated or not a checkpoint."""
    path = Path(path)
    try:
        with np.load(path) as z:
            header = json.loads(bytes(z["header"]).decode())
            if not isinstance(header, dict):
                raise ValueError("the header is not a JSON object")
            groups: dict[str, list[np.ndarray]] = {}
            for key in sorted(k for k in z.files if k != "header"):
                name, _ = key.rsplit("/", 1)
                groups.setdefault(name, []).append(z[key])
    except (OSError, EOFError, ValueError, KeyError, TypeError, AttributeError,
            zipfile.BadZipFile, zlib.error) as exc:
        raise CheckpointError(path, f"cannot read the checkpoint ({type(exc).__name__}: "
                              f"{exc}); it is corrupt or truncated",
                              f"delete {path.name} to train the run again from the start"
                              ) from None
    return groups, header
