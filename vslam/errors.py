"""One exception tree for the whole package: the CLI turns any VslamError into a one-line message."""

from __future__ import annotations

from pathlib import Path


class VslamError(Exception):
    """Root of every error a user can cause (bad input, bad config, missing data)."""


class DatasetError(VslamError):
    """A dataset file is missing or malformed; names the file, the line (1-based) and the problem."""

    def __init__(self, path: str | Path, reason: str, line: int | None = None):
        self.path = Path(path)
        self.line = line
        self.reason = reason
        where = f"{self.path}:{line}" if line is not None else f"{self.path}"
        super().__init__(f"{where}: {reason}")

    def __reduce__(self):  # pickled by its fields (the front-end process sends it to the tracking process)
        return type(self), (self.path, self.reason, self.line)


class ConfigError(VslamError):
    """A config file or override is invalid (unknown key, wrong type)."""


class EvalError(VslamError):
    """Trajectories cannot be evaluated (no overlap, unknown format, too few poses)."""


class InertialError(VslamError):
    """IMU data cannot serve the request (samples do not cover a window, too few samples, a moving 'still' window)."""


class TrackingError(VslamError):
    """A run that produced no measured pose at all (every frame a placeholder)."""
