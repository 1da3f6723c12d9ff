"""How much of its plan a sweep recorded: the poses it stopped at (one frame each), or the passes
it reached when it moved without stopping, against those its manifest says were planned."""

from __future__ import annotations

from typing import Literal, TypedDict

from probecal.core.io.session import Session


class Coverage(TypedDict):
    """Plan steps recorded and planned, counted in ``unit``."""

    recorded: int
    planned: int
    unit: Literal["poses", "passes"]


def sweep_coverage(session: Session) -> Coverage | None:
    """The coverage of a session a sweep recorded from a plan; None for one that states no plan
    (an import)."""
    plan = session.manifest.plan
    if plan is None:
        return None
    if session.manifest.continuous:
        planned = plan.get("passes", 1)
        reached = {r.extra["sweep"] for r in session.records if isinstance(r.extra.get("sweep"), int)}
        recorded = len(reached) if reached else int(len(session) > 0)
        unit: Literal["poses", "passes"] = "passes"
    else:
        planned = plan.get("poses")
        indices = {r.extra["plan_index"] for r in session.records if isinstance(r.extra.get("plan_index"), int)}
        recorded, unit = len(indices) if indices else len(session), "poses"
    if not isinstance(planned, int) or isinstance(planned, bool) or planned < 1:
        return None
    return Coverage(recorded=min(recorded, planned), planned=planned, unit=unit)
