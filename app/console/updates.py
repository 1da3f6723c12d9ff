"""What a page may change: a field's value, of the field's own type.

viser's page sends a field's new value as ``{"value": ...}`` and viser casts it to the type the
field holds; anything else a page sends (another property, a value that cannot be cast, a vector
of another length) would raise inside viser and print a traceback, or set a property the page
never sets (a button's ``disabled``). A dropdown's page sends only its options and a slider's only
numbers within its range, so nothing else is taken for them. The console drops any other update:
the field keeps its value, and the value a number field takes is then checked where it is used
(``app.bounds``)."""

from __future__ import annotations

import math
from typing import Any

import viser
from viser import _messages
from viser.infra import ClientId


def _castable(current: Any, value: Any) -> bool:
    """Whether ``value`` is what viser can make into a value of ``current``'s type."""
    try:
        if isinstance(current, tuple):
            if not isinstance(value, (list, tuple)) or len(value) != len(current):
                return False
            for item in value if current else ():
                type(current[0])(item)
        else:
            type(current)(value)
    except (TypeError, ValueError, OverflowError):
        return False
    return True


def takes(handle: Any, value: Any) -> bool:
    """Whether the field ``handle`` may take ``value`` from a page: of its type; a dropdown's one of
    its options; a slider's a finite number within its range (its page sends no other)."""
    if not _castable(handle._impl.value, value):
        return False
    if isinstance(handle, viser.GuiDropdownHandle):
        return value in handle.options
    if isinstance(handle, viser.GuiSliderHandle):
        return math.isfinite(float(value)) and handle.min <= float(value) <= handle.max
    return True


def guard_updates(server: viser.ViserServer) -> None:
    """Let only a field's value that it :func:`takes` through to viser's handler of the updates a
    page sends."""
    gui = server.gui
    handler = gui._handle_gui_updates
    interface = gui._websock_interface  # the viser version pinned in pyproject.toml

    async def guarded(client_id: ClientId, message: _messages.GuiUpdateMessage) -> None:
        handle = gui._gui_input_handle_from_uuid.get(message.uuid)
        if handle is None or set(message.updates) != {"value"} or not takes(handle, message.updates["value"]):
            return
        await handler(client_id, message)

    interface.unregister_handler(_messages.GuiUpdateMessage, handler)
    interface.register_handler(_messages.GuiUpdateMessage, guarded)
