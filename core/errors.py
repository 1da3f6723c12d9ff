"""The one exception type that the command line turns into exit code 2 and a single line."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import NoReturn


class InputError(Exception):
    """Bad user input: a missing, malformed or inconsistent file.

    The message names the file and the problem, on one line.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = " ".join(problem.split())  # a library's message may run to several lines
        super().__init__(f"{self.path}: {self.problem}" if self.path is not None else self.problem)

    def __reduce__(self) -> tuple[type[InputError], tuple[object, ...]]:
        """Rebuilt from its path and problem: it may cross to another process (a pool worker's)."""
        return type(self), (self.path, self.problem)


class Interrupted(Exception):
    """Long work ended at the user's request: its progress callback raised it (the console's Stop)."""


class DeviceError(RuntimeError):
    """A robot or an image stream failed or refused (core.robot.simulated.RobotError,
    core.acquisition.imagesource.ImageSourceError); the message names the device, on one line."""


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (exit code 2), as bad input is reported."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")
