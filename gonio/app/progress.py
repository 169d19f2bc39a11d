"""A rich progress bar over a session's poses: a subscriber of the engine's documents."""

from __future__ import annotations

from typing import Any

__all__ = ["SessionProgress"]


class SessionProgress:
    """Counts poses and shots from the documents; prints skips and faults.

    Use as a context manager and pass it to the session API as a subscriber; the
    ``start`` document sets the total and the poses already done.
    """

    def __init__(self, quiet: bool, total: int | None = None, done: int = 0) -> None:
        from gonio.progress import task_progress

        self.quiet = quiet
        self.progress = task_progress("[bold]poses", "shots {task.fields[shots]}", disable=quiet)
        self.task = self.progress.add_task("poses", total=total, completed=done, shots=0)
        self.shots = 0
        self.skipped = 0
        self._reduction_error: str | None = None

    def __call__(self, rec: dict[str, Any]) -> None:
        from rich.markup import escape  # a reason or an error may hold brackets: not markup

        t = rec.get("type")
        if t == "start":
            self.progress.update(self.task, total=rec.get("poses"), completed=rec.get("done", 0))
        elif t == "shot":
            self.shots += 1
            self.progress.update(self.task, shots=self.shots)
        elif t in ("pose_done", "pose_skipped"):
            # a skipped pose is finished too: without this the bar stopped short of 100 %
            self.progress.advance(self.task)
            if t == "pose_skipped":
                self.skipped += 1
                self.progress.console.print(
                    f"[yellow]pose {rec.get('pose')} skipped: {escape(str(rec.get('reason')))}"
                )
        elif t == "adaptive_round":
            # an adaptive session's poses are chosen as it goes: each round adds its batch
            # (the start document counted the seed design only; the bar read 50/26)
            total = next(tk.total for tk in self.progress.tasks if tk.id == self.task)
            if total is not None and rec.get("steps"):
                self.progress.update(self.task, total=total + len(rec["steps"]))
            # a round that could not reduce its poses chooses blind: say so (once a cause)
            why = rec.get("reduction_error")
            if why and why != self._reduction_error:
                self._reduction_error = why
                batch = " and the batch is chosen space-filling" if rec.get("steps") else ""
                self.progress.console.print(
                    f"[yellow]adaptive round {rec.get('round')}: the poses so far could not be "
                    f"reduced, so nothing was fitted{batch}: {escape(str(why))}"
                )
        elif t == "fault":
            self.progress.console.print(
                f"[red]fault ({escape(str(rec.get('source')))}): {escape(str(rec.get('error')))}"
            )

    def __enter__(self) -> SessionProgress:
        self.progress.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.__exit__(*exc)
