"""The operator as a target changer: a real rig's mirror is put in place by hand.

A simulated camera swaps targets itself; on a real rig the rig calibration's mirror
(and, later, anything else the rig cannot swap) is put in the sample's place by the
person at the terminal.  :class:`OperatorTargetChanger` asks for it and waits for
Enter, so the session shoots only once the operator has said it is done.  It needs a
terminal: without one it refuses before anything moves (a prompt nobody can answer
would hang the session).
"""

from __future__ import annotations

import sys
from collections.abc import Callable

from gonio.errors import SessionError

__all__ = ["OperatorTargetChanger", "TARGET_WORDS"]

#: What the operator is asked to put in the sample's place, per target kind.
TARGET_WORDS = {
    "sample": "the SAMPLE back on the holder",
    "mirror": "the flat calibration MIRROR in the sample's place (flush with the board)",
    "reference": "the REFERENCE target in the sample's place",
    "flat": "the FLAT-FIELD panel (uniform diffuse light) over the camera's lens",
}


class OperatorTargetChanger:
    """Asks the operator to change the target, and waits until they confirm.

    Parameters
    ----------
    ask
        Shows a prompt and returns the operator's answer (``input`` by default);
        ``EOFError`` or ``KeyboardInterrupt`` from it stop the session.
    interactive
        Whether someone can answer (default: standard input is a terminal).

    Raises
    ------
    SessionError
        At construction when nobody can answer.
    """

    def __init__(
        self, ask: Callable[[str], str] = input, *, interactive: bool | None = None
    ) -> None:
        if interactive is None:
            interactive = sys.stdin is not None and sys.stdin.isatty()
        if not interactive:
            raise SessionError(
                "the plan needs the calibration mirror put in by hand, and standard input "
                "is not a terminal: run the session from a terminal (the session asks "
                "before each change and waits for Enter)"
            )
        self._ask = ask
        self.current = "sample"
        self.asked: list[str] = []

    def set_target(self, kind: str) -> None:
        """Ask for ``kind`` in the sample's place (nothing when it is already there)."""
        if kind not in TARGET_WORDS:
            raise SessionError(f"target must be one of {sorted(TARGET_WORDS)}, got {kind!r}")
        if kind == self.current:
            return
        try:
            self._ask(f"\nPut {TARGET_WORDS[kind]}, then press Enter: ")
        except (EOFError, KeyboardInterrupt) as exc:
            raise SessionError(
                f"stopped while waiting for the operator to put in {TARGET_WORDS[kind]}"
            ) from exc
        self.asked.append(kind)
        self.current = kind
