"""A Ctrl-C whose KeyboardInterrupt a garbage-collector callback swallows is still honoured.

The interpreter runs Python signal handlers at the next bytecode of the main thread; when
that bytecode is in a ``gc.callbacks`` function, the exception is printed as "Exception
ignored" and lost (distributed's GCDiagnosis did this in CI: ``gonio fit`` exited 0 after a
Ctrl-C).  The callbacks below raise SIGINT themselves, so the loss is certain, not timed.
"""

from __future__ import annotations

import gc
import signal
import sys

import pytest

from gonio import cli, interrupts
from gonio.distributed import map_tasks


@pytest.fixture
def default_sigint():
    """SIGINT at Python's default handler, as in a terminal (a test runner's worker may
    have it ignored, and then :func:`interrupts.noting` rightly does nothing)."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def _swallowing_callback(fired: list[int]):
    """A gc callback that raises SIGINT once, while a noting handler is installed."""

    def cb(phase, info):
        if fired or phase != "start":
            return
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            return  # not yet inside interrupts.noting()
        fired.append(1)
        signal.raise_signal(signal.SIGINT)

    return cb


# The swallowed exception reaches sys.unraisablehook, which pytest reports as a warning.
pytestmark = pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")


def test_swallowed_interrupt_is_noted(default_sigint, monkeypatch):
    reported: list[object] = []  # what would be printed as "Exception ignored in ..."
    monkeypatch.setattr(sys, "unraisablehook", lambda u: reported.append(u.exc_type))
    fired: list[int] = []
    cb = _swallowing_callback(fired)
    with interrupts.noting():
        assert not interrupts.noted()
        gc.callbacks.append(cb)
        try:
            gc.collect()  # SIGINT raised inside the callback: swallowed, not raised here
        finally:
            gc.callbacks.remove(cb)
        assert fired == [1]
        assert interrupts.noted()
        assert reported == []  # no traceback on the terminal for the lost interrupt
        gc.callbacks.append(lambda phase, info: 1 / 0)
        try:
            gc.collect()
        finally:
            gc.callbacks.pop()
        assert reported[:1] == [ZeroDivisionError]  # any other unraisable still reported
    assert not interrupts.noted()  # the note belongs to the block
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_an_unswallowed_interrupt_still_raises(default_sigint):
    with pytest.raises(KeyboardInterrupt), interrupts.noting():
        signal.raise_signal(signal.SIGINT)


def test_noting_leaves_a_callers_own_handler_alone():
    seen: list[int] = []
    old = signal.signal(signal.SIGINT, lambda s, f: seen.append(s))
    try:
        with interrupts.noting():
            signal.raise_signal(signal.SIGINT)
            assert not interrupts.noted()
        assert seen == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, old)


def test_cli_exits_130_when_the_interrupt_was_swallowed(default_sigint, capsys):
    """The command ran to its end, but the user asked to stop: exit 130, not 0."""
    fired: list[int] = []
    cb = _swallowing_callback(fired)
    threshold = gc.get_threshold()
    gc.callbacks.append(cb)
    gc.set_threshold(1)  # a collection at the command's first allocations
    try:
        code = cli.run("--version")
    finally:
        gc.set_threshold(*threshold)
        gc.callbacks.remove(cb)
    assert fired == [1]
    assert code == 130
    assert "interrupted" in capsys.readouterr().err


def _swallow_one_interrupt() -> None:
    fired: list[int] = []
    cb = _swallowing_callback(fired)
    gc.callbacks.append(cb)
    try:
        gc.collect()
    finally:
        gc.callbacks.remove(cb)
    assert fired == [1]


def _slow_square(x: int) -> int:
    import time

    time.sleep(0.05)
    return x * x


@pytest.fixture(scope="module")
def inproc_client():
    from distributed import Client

    with Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as c:
        yield c


def test_map_tasks_stops_for_an_interrupt_lost_before_it(default_sigint, inproc_client):
    ran: list[object] = []
    with interrupts.noting():
        _swallow_one_interrupt()
        with pytest.raises(KeyboardInterrupt):
            map_tasks(inproc_client, _slow_square, range(4), key_of=str,
                      progress=lambda *a: ran.append(a))  # fmt: skip
    assert ran == []  # nothing submitted, nothing reported


def test_map_tasks_stops_for_an_interrupt_lost_while_it_waits(default_sigint, inproc_client):
    """The first result's progress callback loses a Ctrl-C to the garbage collector: the
    loop stops at the next result instead of running all 12 tasks."""
    ran: list[object] = []

    def progress(key, outcome, done, total):
        ran.append(key)
        if done == 1:
            _swallow_one_interrupt()

    with interrupts.noting(), pytest.raises(KeyboardInterrupt):
        map_tasks(inproc_client, _slow_square, range(12), key_of=str, progress=progress)
    assert len(ran) == 1
