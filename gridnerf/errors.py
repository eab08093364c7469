"""User-facing errors. Each names the offending file and says what to do.

The CLI catches `GridNerfError`, prints its message on one line and exits
with status 2, so no traceback hides the fix from the user.
"""

from __future__ import annotations

from pathlib import Path


class GridNerfError(Exception):
    """Base class for errors caused by input a user can fix."""

    def __init__(self, path: str | Path | None, problem: str, fix: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        self.fix = fix
        where = f"{self.path}: " if self.path else ""
        super().__init__(f"{where}{problem}. Fix: {fix}")


class RawError(GridNerfError):
    """A RAW/DNG file is missing, corrupt or unsupported."""


class SceneError(GridNerfError):
    """A scene folder is inconsistent (poses, sizes, splits)."""


class PoseError(SceneError):
    """Camera poses are missing, non-finite or not rigid."""


class NumericsError(GridNerfError):
    """Training produced NaN/Inf; nothing non-finite is ever checkpointed."""


class ConfigError(GridNerfError, ValueError):
    """A preset, `--set` override or saved config.json is invalid (names field and values)."""


class CheckpointError(GridNerfError):
    """A checkpoint cannot be read, written or does not fit the run's config."""


class WriteError(GridNerfError):
    """A file cannot be written (disk full, permissions); the previous version is kept."""


class RunLockedError(GridNerfError):
    """Another process is training in the same run folder."""
