"""The one exception type that the command line turns into exit code 2 and a single line."""

from __future__ import annotations

from enum import Enum
from pathlib import Path

QUOTED_CHARS = 60
"""The most of a value from outside (a name, a status, a field) a message quotes."""


def quoted(text: str, limit: int = QUOTED_CHARS) -> str:
    """A value from outside, quoted and cut to one short line for a message: however long or
    whatever characters it holds, the message stays one line of bounded length."""
    return repr(text) if len(text) <= limit else f"{text[:limit]!r}..."


class Remedy(Enum):
    """What the user can do about an :class:`InputError` beyond what its message says in domain
    words: the command line names the option that does it (``app.cli``); the console, where the
    option has no control, says nothing more."""

    FORCE = "apply or overwrite anyway"
    START_DEPTH = "record the images' first row's depth below the probe's face"
    SPACING = "give the scanner's nominal pixel spacing"
    IMAGE_EXTENT = "give the image's depth and width"
    REGISTER = "find the object's pose by registering the CAD model"
    CONTINUOUS = "record with continuous motion, keeping the pose stream"
    SWEEP_TIMING = "set the pass speed, the frame rate and the image latency"
    ARM = "name the arm that recorded the poses"


class InputError(Exception):
    """Bad user input: a missing, malformed or inconsistent file.

    The message names the file and the problem, on one line.
    """

    def __init__(self, path: str | Path | None, problem: str, remedies: tuple[Remedy, ...] = ()):
        self.path = None if path is None else Path(path)
        self.problem = " ".join(problem.split())  # a library's message may run to several lines
        self.remedies = remedies
        super().__init__(f"{self.path}: {self.problem}" if self.path is not None else self.problem)

    def __reduce__(self) -> tuple[type[InputError], tuple[object, ...]]:
        """Rebuilt from its path, problem and remedies: it may cross to another process (a pool
        worker's)."""
        return type(self), (self.path, self.problem, self.remedies)


class Interrupted(Exception):
    """Long work ended at the user's request: its progress callback raised it (the console's Stop)."""


class DeviceError(RuntimeError):
    """A robot or an image stream failed or refused (core.robot.simulated.RobotError,
    core.acquisition.imagesource.ImageSourceError); the message names the device, on one line."""

