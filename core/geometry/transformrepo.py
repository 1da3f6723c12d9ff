"""Named frames joined by transforms, as PLUS's transform repository joins them.

A PLUS recording holds per frame some ``<From>To<To>`` transforms (``ProbeToTracker``,
``TemplateToStepperHome``, ...) and a device set holds constant ones (``PhantomToReference``,
``ImageToProbe``). Each is an edge between two named frames. Any ``a_to_b`` is then found by a
breadth-first search from a to b, composing the transforms along the path and inverting those
walked against their direction; a frame's result is valid only where every transform on the path
is. Matrices are 4x4, mm, ``a_to_b`` maps frame-a coordinates into frame b.
"""

from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from probecal.core.geometry.transforms import MAX_CONDITION

_TO = re.compile(r"(?=To[^a-z])")


def frame_splits(name: str) -> list[tuple[str, str]]:
    """Every (from, to) reading of a transform name such as ``ProbeToStepperHome``.

    PLUS (igsioTransformName) splits a name at a "To" followed by a character that is not a
    lower-case letter, with a frame name on either side: ``ToolToTracker`` is Tool -> Tracker,
    ``ProbeToStepperHome`` is Probe -> StepperHome, ``ProbeToTopView`` is Probe -> TopView. PLUS
    refuses a name with more than one such "To" (``HeadToTopToF``); here each reading is returned
    and :func:`pick_split` chooses.
    """
    return [(name[: m.start()], name[m.start() + 2 :]) for m in _TO.finditer(name) if m.start() > 0]


def pick_split(name: str, known: Iterable[str]) -> tuple[str, str] | None:
    """The (from, to) reading of ``name``: its only one, or else the one naming more of the
    ``known`` frames (those other transforms join) than any other reading does, so that the
    transform connects to the rest; None when the name has no reading or no reading is preferred."""
    candidates = frame_splits(name)
    if len(candidates) <= 1:
        return candidates[0] if candidates else None
    known = set(known)
    scores = [sum(frame in known for frame in pair) for pair in candidates]
    best = max(scores)
    return candidates[scores.index(best)] if best > 0 and scores.count(best) == 1 else None


def _shown_names(names: Iterable[str], most: int) -> str:
    """Names for a one-line message: sorted, quoted when unprintable or long, the first ``most``."""
    names = sorted(names)
    shown = [n if n.isprintable() and len(n) <= 30 else repr(n[:30]) for n in names[:most]]
    more = f" and {len(names) - most} more" if len(names) > most else ""
    return ", ".join(shown) + more if names else "none"


@dataclass(frozen=True)
class Link:
    """A stored ``source_to_target``: (N, 4, 4) matrices, mm, and (N,) valid flags; ``name`` as
    the file spells it (``ProbeToStepperHome``)."""

    name: str
    source: str
    target: str
    matrices: np.ndarray
    valid: np.ndarray


@dataclass(frozen=True)
class Composed:
    """``source_to_target`` found through the repository: (N, 4, 4) matrices, mm (NaN where not
    valid), (N,) valid, and the ``path`` as a product of stored transforms, e.g.
    ``inv(TemplateToStepperHome) @ ProbeToStepperHome``."""

    matrices: np.ndarray
    valid: np.ndarray
    path: str


def _inverse(matrices: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame inverses of (N, 4, 4) matrices and where they are valid: a frame whose matrix is
    singular (condition number over MAX_CONDITION) has no inverse and loses its validity."""
    usable = np.where(valid[:, None, None], matrices, np.eye(4))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        invertible = valid & (np.linalg.cond(usable) <= MAX_CONDITION)
    return np.linalg.inv(np.where(invertible[:, None, None], usable, np.eye(4))), invertible


class TransformRepository:
    """The transforms of a recording of ``n`` frames as a graph of frame names; ``unread`` are
    the transform names that give no frame pair (see :func:`pick_split`), left out of it."""

    def __init__(self, n: int, links: list[Link], unread: list[str]):
        self.n = n
        self.unread = unread
        self._edges: dict[str, list[tuple[str, Link, bool]]] = {}
        for link in links:
            self._edges.setdefault(link.source, []).append((link.target, link, True))
            self._edges.setdefault(link.target, []).append((link.source, link, False))

    @classmethod
    def build(
        cls,
        n: int,
        transforms: Mapping[str, np.ndarray],
        statuses: Mapping[str, np.ndarray],
        constants: Mapping[tuple[str, str], np.ndarray] | None = None,
    ) -> TransformRepository:
        """A repository of per-frame ``transforms`` (name -> (n, 4, 4), with (n,) ``statuses``)
        and ``constants`` ((from, to) -> 4x4, valid at every frame, as a device set's
        CoordinateDefinitions hold them). The search prefers the per-frame transforms, then the
        constants, each in the order given, among paths of the same length."""
        constants = constants or {}
        known = {frame for pair in constants for frame in pair}
        known |= {frame for name in transforms if len(pairs := frame_splits(name)) == 1 for frame in pairs[0]}
        links, unread = [], []
        for name, matrices in transforms.items():
            pair = pick_split(name, known)
            if pair is None:
                unread.append(name)
            else:
                links.append(Link(name, *pair, matrices, statuses[name]))
        for (source, target), matrix in constants.items():
            every_frame = np.broadcast_to(matrix, (n, 4, 4))
            links.append(Link(f"{source}To{target}", source, target, every_frame, np.ones(n, bool)))
        return cls(n, links, unread)

    @property
    def frames(self) -> set[str]:
        """Every frame some transform names."""
        return set(self._edges)

    def describe(self) -> str:
        """The frames the transforms name and any unread names, for a one-line message."""
        unread = f"; names read as no frame pair: {_shown_names(self.unread, 3)}" if self.unread else ""
        return f"the transforms held name the frames {_shown_names(self.frames, 10)}{unread}"

    def find(self, source: str, target: str) -> Composed | None:
        """``source_to_target`` along a shortest path of stored transforms (NaN where not valid),
        or None when no path joins the two frames."""
        if source not in self._edges:
            return None
        came_from: dict[str, tuple[str, Link, bool] | None] = {source: None}
        queue = deque([source])
        while queue and target not in came_from:
            frame = queue.popleft()
            for there, link, forward in self._edges[frame]:
                if there not in came_from:
                    came_from[there] = (frame, link, forward)
                    queue.append(there)
        if target not in came_from:
            return None
        matrices, valid, factors = np.broadcast_to(np.eye(4), (self.n, 4, 4)), np.ones(self.n, bool), []
        step = came_from[target]
        while step is not None:  # from the target back: each earlier step multiplies on the right
            frame, link, forward = step
            step_matrices, step_valid = (link.matrices, link.valid) if forward else _inverse(link.matrices, link.valid)
            matrices = matrices @ step_matrices
            valid = valid & step_valid
            factors.append(link.name if forward else f"inv({link.name})")
            step = came_from[frame]
        matrices = np.array(matrices)
        matrices[~valid] = np.nan
        return Composed(matrices, valid, " @ ".join(factors) or "identity")
