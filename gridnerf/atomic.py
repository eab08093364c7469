"""The package's one atomic file write.

Every file gridnerf writes (checkpoints, configs, metrics, images, DNGs, transforms.json,
simulated scenes) goes to `<name>.tmp` in the destination folder, is flushed to disk and
then moved onto `<name>` with `os.replace`, which is atomic on POSIX file systems: a crash
or a kill leaves either the old file or the new one, never a half-written file that looks
valid. The `.tmp` is removed on any failure; an OSError (disk full, read-only folder)
becomes a WriteError naming the file, so the CLI prints one line and exits with status 2.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

from gridnerf.errors import WriteError


def write(path: str | Path, fill: Callable[[Path], None]) -> None:
    """Atomically create or replace `path` with what `fill(tmp_path)` writes to tmp_path."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fill(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as exc:
        raise WriteError(path, f"cannot write the file ({exc.strerror or exc}); the "
                         "previous version is kept", "free disk space or fix the folder's "
                         "permissions, then rerun (training resumes from the last "
                         "checkpoint)") from None
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | Path, data: bytes) -> None:
    write(path, lambda tmp: tmp.write_bytes(data))


def write_text(path: str | Path, text: str) -> None:
    write_bytes(path, text.encode())
