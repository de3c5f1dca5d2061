"""Options as typed frozen dataclasses that refuse unknown keys: the one check they share."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import fields

from bluesky_offsets.errors import InputError


def refuse_unknown(cls, given: Iterable[str], what: str) -> None:
    """Raise ``InputError("<what> [unknown keys]; known: [fields]")`` for keys ``cls`` does not take.

    It is raised when ``given`` names a key that is not an init field of the dataclass ``cls``.
    """
    known = {f.name for f in fields(cls) if f.init}
    unknown = sorted(set(given) - known)
    if unknown:
        raise InputError(f"{what} {unknown}; known: {sorted(known)}")
