"""The command line's argument parser: usage errors on one line, as bad input is reported."""

from __future__ import annotations

import argparse


class OneLineParser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line (exit code 2), as bad input is reported."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")
