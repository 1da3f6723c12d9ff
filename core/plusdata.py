"""Where the PLUS toolkit's public test recordings are, for the real-data tests and benchmarks.

One setting: the folder named by the environment variable ``PROBECAL_PLUS_DATA``, by default
``../shared/data/plus`` beside this repository. The files are those of the public
PlusToolkit/PlusLibData repository at the commit the README names (section "Real data"), in its
layout (``TestImages/``, ``ConfigFiles/``, ``CADModels/``).
"""

from __future__ import annotations

import os
from pathlib import Path

ENV = "PROBECAL_PLUS_DATA"
DEFAULT = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "plus"


def plus_data_dir() -> Path:
    """The PLUS data folder the setting names (it may not exist)."""
    value = os.environ.get(ENV)
    return Path(value).expanduser() if value else DEFAULT


def missing_reason() -> str | None:
    """Why the PLUS data cannot be used, naming the setting, or None when it is there."""
    folder = plus_data_dir()
    if (folder / "TestImages").is_dir():
        return None
    return (f"the real PLUS recordings are not at {folder}: set {ENV} to a copy of PlusLibData "
            f"(README, 'Real data')")
