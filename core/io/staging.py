"""An import's session: written under another name, read back, and only then put in place."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from probecal.core.errors import InputError
from probecal.core.geometry.phantom import Phantom
from probecal.core.io.files import staged_folder
from probecal.core.io.manifest import Manifest
from probecal.core.io.session import RefusedRecord, SessionWriter, load_session


@contextmanager
def imported_session(out: Path, source: Path, manifest: Manifest, phantom: Phantom | None) -> Iterator[SessionWriter]:
    """A writer of the session that an import of ``source`` makes at ``out``: the session is
    written beside ``out`` (as ``.NAME.importing``, refused when a leftover is there), read back
    as any command would read it, and renamed into place only then. When the block raises, or
    what it wrote does not read back (an InputError naming ``source`` and the problem), nothing
    is left at ``out``."""
    staging = out.with_name(f".{out.name}.importing")
    with staged_folder(out, staging, "import") as folder:
        with SessionWriter(folder, manifest, phantom=phantom) as writer:
            try:
                yield writer
            except RefusedRecord as exc:  # a record its reader would refuse: the source's fault
                raise InputError(source, f"does not make a session that reads back: {exc.problem}") from None
        try:
            load_session(folder)
        except InputError as exc:
            raise InputError(source, f"does not make a session that reads back: {exc.problem}") from None

