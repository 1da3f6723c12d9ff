"""The page's text boundary: the one place where text reaches the page as HTML.

viser renders an HTML element's content as raw HTML, and a markdown element's as markdown that
may hold raw HTML: a session folder named ``<img src=x onerror=...>``, a manifest field, a
tracker's device name or an error message quoting any of them would run script in every tab.
So every box the console writes into is a :class:`TextBox`, and everything it is given is
escaped here, unless it is :class:`Markup`: HTML the console's own templates built with
:func:`html`, which escapes every value it puts in (markupsafe's ``Markup.format``). Nothing else
in the console sets an element's content (``tests/test_attack_markup.py`` holds it so).
"""

from __future__ import annotations

import re

import viser
from markupsafe import Markup, escape

__all__ = ["Markup", "TextBox", "html", "text_box"]

TAG = re.compile(r"<[^>]*>")


def html(template: str, *values: object) -> Markup:
    """``template`` (the console's own HTML, with ``{}`` fields) with ``values`` put in, each
    escaped unless it is :class:`Markup` already."""
    return Markup(template).format(*values)


class TextBox:
    """A box of the page that shows text: a plain ``str`` shows as typed, :class:`Markup` as the
    HTML it is. Unchanged content is not sent again (every re-render costs the browser time)."""

    def __init__(self, handle: viser.GuiHtmlHandle):
        self._handle = handle

    def show(self, content: str) -> None:
        shown = str(escape(content))
        if self._handle.content != shown:
            self._handle.content = shown

    @property
    def content(self) -> Markup:
        """What the box shows, as the HTML it is."""
        return Markup(self._handle.content)

    @property
    def text(self) -> str:
        """What the box shows, as the reader sees it: its text without the markup, whitespace
        runs as one space."""
        return " ".join(Markup(TAG.sub(" ", self._handle.content)).unescape().split())

    @property
    def visible(self) -> bool:
        return self._handle.visible

    @visible.setter
    def visible(self, visible: bool) -> None:
        self._handle.visible = visible


def text_box(gui: viser.GuiApi, content: str, visible: bool = True) -> TextBox:
    """A new box in ``gui``'s current container showing ``content`` (escaped unless Markup)."""
    return TextBox(gui.add_html(str(escape(content)), visible=visible))
