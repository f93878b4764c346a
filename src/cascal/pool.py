"""Local worker processes that leave Ctrl-C to the command.

A terminal sends SIGINT to the whole process group: workers that took it too would print
tracebacks (while they import NumPy at their start, or mid-task), and a second Ctrl-C
that interrupted the wait for them could hang the process at exit. So workers start with
SIGINT blocked and then ignore it (:func:`ignore_interrupts` in their initializer); the
command shuts them down on the first Ctrl-C (:func:`shutdown`), and a second one stops
them at once. While the command waits for results (:func:`completed`), Ctrl-C and SIGTERM
are taken between waits, never inside one: a second Ctrl-C hard on the first had broken
the wait's lock ("release unlocked lock").
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
import threading
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait

#: Whether this platform has signal masks (POSIX; not Windows).
_MASKS = hasattr(signal, "pthread_sigmask")


class Terminated(KeyboardInterrupt):
    """SIGTERM (``kill``, a batch system's end of a job), taken as a Ctrl-C is: raised where
    :func:`raise_terminated` handles SIGTERM (the ``cascal`` command), and inside
    :func:`deferred_signals`, which ends the process by the signal after all where SIGTERM
    had its default action."""


def raise_terminated(signum, frame) -> None:
    """A SIGTERM handler: raise :class:`Terminated` (the command's, from its start)."""
    raise Terminated


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Within (a command): SIGTERM raises :class:`Terminated` where it had its default
    action, so the command leaves its outputs whole; restored on leaving (the command
    called from a program of its own). Only in the main thread."""
    own = _main_thread() and signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
    if own:
        signal.signal(signal.SIGTERM, raise_terminated)
    try:
        yield
    finally:
        if own and signal.getsignal(signal.SIGTERM) in (raise_terminated, signal.SIG_IGN):
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


def stop_listening() -> None:
    """Ignore further Ctrl-C (:func:`ignore_interrupts`), and SIGTERM where
    :func:`raise_terminated` handles it: the command is ending with its message (a
    program's own SIGTERM handler stays)."""
    ignore_interrupts()
    if _main_thread() and signal.getsignal(signal.SIGTERM) is raise_terminated:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


#: Most local worker processes a command or study starts: each imports NumPy and SciPy
#: (a review: --workers 3000000000 crashed inside multiprocessing, and 100000 started one
#: process per task).
MAX_WORKERS = 256


def default_workers() -> int:
    """Worker processes by default: the CPUs this process may run on (its affinity, where
    the OS tells it: a review's fleet pinned to one CPU started two), at most
    :data:`MAX_WORKERS`."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # (not on every OS)
        n = os.cpu_count() or 1
    return max(1, min(n, MAX_WORKERS))


def spawn_pool(n_workers: int, initializer: Callable[..., None], initargs: tuple = ()):
    """A pool of ``n_workers`` spawned processes (none shares the parent's state);
    ``initializer`` should call :func:`ignore_interrupts`."""
    ctx = multiprocessing.get_context("spawn")
    return ProcessPoolExecutor(
        n_workers, mp_context=ctx, initializer=initializer, initargs=initargs
    )


def submit_all(pool: ProcessPoolExecutor, fn: Callable, calls: Iterable[tuple]) -> list[Future]:
    """``pool.submit(fn, *args)`` for each ``args`` of ``calls``. The workers start as the
    tasks are submitted: meanwhile SIGINT is blocked in this thread, which they inherit,
    so a Ctrl-C while they import NumPy stays with the command; and a Ctrl-C that another
    thread takes (BLAS's) is held until the tasks are submitted, not raised while a
    worker is being handed its start-up data (which it would then miss)."""
    if not (_main_thread() and _MASKS) or signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return [pool.submit(fn, *args) for args in calls]
    held: list[int] = []
    with _handling_interrupts(lambda signum, frame: held.append(signum)):
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            futures = [pool.submit(fn, *args) for args in calls]
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
    if held:  # now, as it would have come
        signal.raise_signal(signal.SIGINT)
    return futures


def ignore_interrupts() -> None:
    """Ignore SIGINT from now on, and unblock it: in a worker's initializer (a Ctrl-C
    pending since the worker's start is dropped), or in a command that ends interrupted
    (a further Ctrl-C while it exits changes nothing). Only in the main thread."""
    if not _main_thread():
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if _MASKS:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def shutdown(pool: ProcessPoolExecutor, *, wait_for_tasks: bool, interrupted: bool) -> bool:
    """Shut ``pool`` down, cancelling the tasks not started. ``wait_for_tasks``: let the
    tasks under way finish; otherwise stop the workers now. A Ctrl-C during the wait stops
    the workers instead of interrupting it (an interrupted wait could hang the process at
    exit); where the caller is not handling one already (``interrupted``), it is raised
    after, as KeyboardInterrupt. Returns True where the workers were stopped (their tasks
    unfinished)."""
    stopped: list[bool] = []
    signals: list[int] = []

    def on_interrupt(signum, frame) -> None:
        signals.append(signum)
        _terminate(pool, stopped)

    with _handling_interrupts(on_interrupt):
        if not wait_for_tasks:
            _terminate(pool, stopped)
        pool.shutdown(wait=True, cancel_futures=True)
    if signals and not interrupted:
        raise KeyboardInterrupt
    return bool(stopped)


@contextlib.contextmanager
def deferred_signals() -> Iterator[list[int]]:
    """Within: SIGINT and SIGTERM are recorded in the list this yields instead of acting at
    once (only where they would end the process or the command: the default handlers, and
    :func:`raise_terminated`; in the main thread). :func:`raise_signals` raises them where
    the caller chooses; any left at the end are raised there, unless an exception is under
    way. A SIGTERM whose action was the default is delivered again on leaving, once the
    handlers are restored: the process then ends by it, as it would have, its workers
    stopped first."""
    got: list[int] = []
    if not _main_thread():
        yield got
        return
    ours = {
        signal.SIGINT: (signal.default_int_handler,),
        signal.SIGTERM: (signal.SIG_DFL, raise_terminated),
    }
    previous = {}
    for signum, handlers in ours.items():
        if signal.getsignal(signum) in handlers:
            previous[signum] = signal.signal(signum, lambda signum, frame: got.append(signum))
    hook = threading.excepthook
    threading.excepthook = _quiet_when_stopping(got, hook)
    try:
        yield got
        raise_signals(got)
    except Terminated:
        if previous.get(signal.SIGTERM) is signal.SIG_DFL:
            for signum, handler in previous.items():
                signal.signal(signum, handler)
            signal.raise_signal(signal.SIGTERM)  # (the process ends here)
        raise
    finally:
        threading.excepthook = hook
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def _quiet_when_stopping(got: list[int], hook: Callable) -> Callable:
    """``threading.excepthook`` that drops the exceptions of a process pool's manager
    thread once a signal in ``got`` stops the command: a SIGTERM to the process group
    while workers start can break the pool under that thread, which in CPython 3.11 then
    fails on its own ("dictionary changed size during iteration"), a traceback in the
    middle of the command's "terminated"; the pool is being shut down anyway."""

    def quiet(args) -> None:
        if got and type(args.thread).__name__ == "_ExecutorManagerThread":
            return
        hook(args)

    return quiet


def raise_signals(got: list[int]) -> None:
    """Raise what :func:`deferred_signals` recorded: :class:`Terminated` where SIGTERM came,
    else KeyboardInterrupt where SIGINT did; nothing where none came."""
    if got:
        raise Terminated if signal.SIGTERM in got else KeyboardInterrupt


def completed(futures: list[Future], got: list[int], poll_s: float = 0.2) -> Iterator[Future]:
    """Yield ``futures`` as they finish (those finishing together in list order), raising
    the signals that :func:`deferred_signals` recorded in ``got`` between the waits (each
    wait at most ``poll_s`` seconds)."""
    order = {id(f): i for i, f in enumerate(futures)}
    pending = set(futures)
    while pending:
        raise_signals(got)
        done, pending = wait(pending, timeout=poll_s, return_when=FIRST_COMPLETED)
        raise_signals(got)
        yield from sorted(done, key=lambda f: order[id(f)])


@contextlib.contextmanager
def _handling_interrupts(handler: Callable) -> Iterator[None]:
    """Within: SIGINT calls ``handler`` instead of raising KeyboardInterrupt. Only in the
    main thread, where Python's signal handlers run."""
    if not _main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _terminate(pool: ProcessPoolExecutor, stopped: list[bool]) -> None:
    stopped.append(True)
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()
