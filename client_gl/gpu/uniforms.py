"""Uniform writes that skip the values a program already holds (a steady frame then writes almost none)."""
from __future__ import annotations

_MISSING = object()


class ProgramUniforms:
    """The uniforms of one program, written only when their value changes.

    A uniform keeps its value in the program object, so the last value written stays until this writer changes it:
    valid while nothing else writes this program's uniforms (each renderer owns its programs). Values are Python
    numbers, tuples, or bytes (written raw: matrices as float32 column-major)."""

    __slots__ = ("_members", "_last")

    def __init__(self, prog):
        self._members = {name: prog[name] for name in prog}
        self._last: dict[str, object] = {}

    def set(self, name: str, value) -> None:
        if self._last.get(name, _MISSING) == value:
            return
        member = self._members.get(name)
        if member is None:  # not an active uniform of this program (optimised away)
            return
        if isinstance(value, bytes):
            member.write(value)
        else:
            member.value = value
        self._last[name] = value

    def forget(self) -> None:
        """Write every value again next time (after something else changed the program's uniforms)."""
        self._last.clear()
