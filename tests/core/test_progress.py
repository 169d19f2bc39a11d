"""The shared progress-bar layout: what a user sees in a bar."""

from __future__ import annotations

import io

from rich.console import Console

from gonio.progress import task_progress


def _render(progress) -> str:
    return progress.console.export_text()


def test_bar_shows_label_count_extra_and_eta():
    console = Console(file=io.StringIO(), width=120, record=True, force_terminal=False)
    with task_progress("[bold]poses", "shots {task.fields[shots]}", console=console) as bar:
        task = bar.add_task("poses", total=5, shots=7)
        bar.update(task, completed=3)
        bar.refresh()
    text = _render(bar)
    assert "poses" in text and "3/5" in text and "shots 7" in text and "ETA" in text


def test_without_eta_no_time_columns():
    console = Console(file=io.StringIO(), width=120, record=True, force_terminal=False)
    with task_progress(eta=False, console=console) as bar:
        task = bar.add_task("dry run", total=4)
        bar.update(task, completed=4)
        bar.refresh()
    text = _render(bar)
    assert "dry run" in text and "4/4" in text and "ETA" not in text and "0:00" not in text
