"""Facts about a protocol, said once per lot rather than as every session's warning.

What a protocol's steps cannot observe (e.g. lever-arm components without tilted steps,
``P_LEVER_ARM_UNOBSERVED``) is the same for every session of that protocol: it is a
*protocol note* (``"P_<CODE>: text"``), kept per session in the sessions table's
``protocol_notes`` column, and it does not make a session "warned" (a session is warned only
for what is wrong with that session). :func:`lot_notes` gathers a lot's distinct notes with the
sessions and units they concern, for the lot report and the run's summary.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class ProtocolNote:
    """One distinct note of a lot: its code, its text (``"P_...: ..."``) and how many
    sessions and units it concerns."""

    code: str
    text: str
    sessions: int
    units: int

    def line(self) -> str:
        """The note as one line, e.g. ``P_LEVER_ARM_UNOBSERVED: ... (225 sessions, 45 units)``."""
        return f"{self.text} ({self.sessions} session(s), {self.units} unit(s))"


def note_code(note: str) -> str:
    """The code of a note (``P_LEVER_ARM_UNOBSERVED`` of ``"P_LEVER_ARM_UNOBSERVED: ..."``)."""
    return str(note).split(":", 1)[0].strip()


def _as_list(v) -> list[str]:
    if v is None:
        return []
    if isinstance(v, (list, tuple, np.ndarray)):
        return [str(x) for x in v]
    if isinstance(v, float) and v != v:
        return []
    return [str(v)]


def notes_of(pairs: Iterable[tuple[str, Iterable[str] | None]]) -> list[ProtocolNote]:
    """The distinct notes of ``(unit, session's notes)`` pairs, in the order first met."""
    sessions: dict[str, int] = {}
    units: dict[str, set[str]] = {}
    for unit, notes in pairs:
        for n in dict.fromkeys(_as_list(notes)):
            sessions[n] = sessions.get(n, 0) + 1
            units.setdefault(n, set()).add(str(unit))
    return [ProtocolNote(note_code(n), n, sessions[n], len(units[n])) for n in sessions]


def lot_notes(sessions: pd.DataFrame | None) -> list[ProtocolNote]:
    """The distinct protocol notes of a lot's sessions table (none when the table is absent
    or was written before the column existed)."""
    if sessions is None or "protocol_notes" not in sessions or not len(sessions):
        return []
    return notes_of(zip(sessions["unit"].astype(str).tolist(), sessions["protocol_notes"].tolist()))
