"""Worker pools that leave Ctrl-C to the command: a Ctrl-C while the pool shuts down."""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
import time
from concurrent.futures import Future

import pytest

from cascal import pool

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


def _sleeping_pool(seconds: float):
    """Two workers, each busy with ``time.sleep(seconds)``, started."""
    ex = pool.spawn_pool(2, pool.ignore_interrupts)
    futures = pool.submit_all(ex, time.sleep, [(seconds,), (seconds,)])
    deadline = time.monotonic() + 60
    while not all(f.running() for f in futures) and time.monotonic() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)  # (running means handed to a worker: let it start sleeping)
    return ex, futures


def _interrupt_in(seconds: float) -> threading.Timer:
    timer = threading.Timer(seconds, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    return timer


@pytest.mark.parametrize("interrupted", [False, True])
def test_a_ctrl_c_while_the_pool_shuts_down_stops_its_workers(interrupted):
    """A review's cases: a Ctrl-C while the command waited for its workers to end hung the
    process at exit (the wait interrupted), and once the study's trials were all stored
    it was taken as a second Ctrl-C and ignored (exit 0). Now it stops the workers, and
    where the command is not handling a Ctrl-C already, it is raised after."""
    signal.signal(signal.SIGINT, signal.default_int_handler)  # (as in a command)
    ex, futures = _sleeping_pool(60.0)
    t0 = time.monotonic()
    _interrupt_in(0.3)
    if interrupted:
        assert pool.shutdown(ex, wait_for_tasks=True, interrupted=True)  # workers stopped
    else:
        with pytest.raises(KeyboardInterrupt):
            pool.shutdown(ex, wait_for_tasks=True, interrupted=False)
    assert time.monotonic() - t0 < 30  # not the tasks' 60 s
    assert all(f.done() for f in futures)
    assert not any(p.is_alive() for p in multiprocessing.active_children())
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # restored


def test_a_pool_shut_down_undisturbed_lets_its_tasks_finish():
    ex, futures = _sleeping_pool(0.5)
    assert not pool.shutdown(ex, wait_for_tasks=True, interrupted=False)
    assert [f.result() for f in futures] == [None, None]


def test_a_ctrl_c_while_tasks_are_submitted_comes_after_them():
    """A Ctrl-C while the workers are being spawned is held until every task is
    submitted (it had cut a worker's start-up data), then raised; the workers, started
    with SIGINT blocked, ignore it."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    ex = pool.spawn_pool(2, pool.ignore_interrupts)
    interrupting = _Interrupting(ex)
    with pytest.raises(KeyboardInterrupt):
        pool.submit_all(interrupting, time.sleep, [(0.2,), (0.2,)])
    assert len(interrupting.made) == 2  # both submitted before the interrupt came
    assert [f.result(timeout=60) for f in interrupting.made] == [None, None]  # workers alive
    pool.shutdown(ex, wait_for_tasks=True, interrupted=False)


class _Interrupting:
    """A pool whose every ``submit`` first sends this process SIGINT, as a Ctrl-C then
    would; it records the futures made."""

    def __init__(self, ex) -> None:
        self.ex, self.made = ex, []

    def submit(self, fn, *args):
        os.kill(os.getpid(), signal.SIGINT)
        self.made.append(self.ex.submit(fn, *args))
        return self.made[-1]


def _never_done(n: int) -> list[Future]:
    return [Future() for _ in range(n)]


@pytest.mark.parametrize("repeat", range(15))
def test_two_ctrl_c_hard_on_each_other_while_waiting_raise_one_interrupt(repeat):
    """A review's case: two SIGINTs back to back while the study waited for results broke
    ``as_completed``'s lock about one time in three ("RuntimeError: release unlocked
    lock", a traceback and exit 1). Now the wait records them and the loop raises one
    KeyboardInterrupt between waits, the handlers then restored."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    futures = _never_done(2)

    def twice() -> None:
        os.kill(os.getpid(), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)

    timer = threading.Timer(0.05 + 0.01 * repeat, twice)
    with pytest.raises(KeyboardInterrupt) as caught:
        with pool.deferred_signals() as got:
            timer.start()
            for _ in pool.completed(futures, got, poll_s=0.05):
                pytest.fail("no future finishes")
    timer.join()
    assert type(caught.value) is KeyboardInterrupt
    assert got in ([signal.SIGINT], [signal.SIGINT] * 2)  # (two pending signals can merge)
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_sigterm_while_waiting_is_raised_as_terminated():
    """Where SIGTERM raises Terminated (the command's handler), the wait raises it between
    waits, and the handler is the command's again after."""
    signal.signal(signal.SIGTERM, pool.raise_terminated)
    try:
        futures = _never_done(1)
        threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGTERM)).start()
        with pytest.raises(pool.Terminated):
            with pool.deferred_signals() as got:
                for _ in pool.completed(futures, got, poll_s=0.05):
                    pass
        assert signal.getsignal(signal.SIGTERM) is pool.raise_terminated
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


def test_a_default_sigterm_ends_the_process_by_the_signal_after_the_cleanup(tmp_path):
    """A review's case: in a program of its own, ``run_study`` turned SIGTERM into a
    KeyboardInterrupt that the program could catch and go on from (or die of with a
    traceback and exit 1). Where SIGTERM has its default action, the process now ends by
    the signal, once the code under way has cleaned up (its workers stopped)."""
    import subprocess

    script = tmp_path / "term.py"
    script.write_text(
        "import os, signal, threading\n"
        "from concurrent.futures import Future\n"
        "from cascal import pool\n"
        "threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)).start()\n"
        "try:\n"
        "    with pool.deferred_signals() as got:\n"
        "        try:\n"
        "            for _ in pool.completed([Future()], got, poll_s=0.05):\n"
        "                pass\n"
        "        finally:\n"
        "            print('cleaned up', flush=True)\n"
        "except KeyboardInterrupt:\n"
        "    print('caught: the program went on', flush=True)\n"
    )
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    assert done.returncode == -signal.SIGTERM, (done.stdout, done.stderr)
    assert done.stdout == "cleaned up\n" and "Traceback" not in done.stderr


def test_completed_yields_in_list_order_and_signals_wait_for_the_caller():
    """Futures finished together come in list order; a signal recorded while the caller
    works on a result is raised at the next wait, and one left at the end on leaving."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    futures = _never_done(3)
    for i in (2, 0, 1):
        futures[i].set_result(i)
    with pytest.raises(KeyboardInterrupt):
        with pool.deferred_signals() as got:
            seen = []
            for fut in pool.completed(futures, got):
                seen.append(fut.result())
                os.kill(os.getpid(), signal.SIGINT)  # handled here: recorded, not raised
                time.sleep(0.01)
            assert seen == [0, 1, 2] and got  # all three yielded: they finished together
    with pytest.raises(KeyboardInterrupt):
        with pool.deferred_signals():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # an ignored Ctrl-C stays ignored
    try:
        with pool.deferred_signals() as got:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.01)
        assert got == []
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def test_a_pool_manager_thread_s_failure_is_quiet_once_a_signal_stops_the_command():
    """A review's case: SIGTERM to the process group while 16 workers started broke the
    pool under its manager thread, which in CPython 3.11 then failed on its own (a
    thread's traceback, 1 run in 12, before "terminated"). While a signal stops the
    command, that thread's exceptions are dropped; others still reach the hook."""
    seen = []

    class _ExecutorManagerThread:  # the name CPython gives the pool's manager thread
        pass

    def args(thread):
        return threading.ExceptHookArgs((RuntimeError, RuntimeError("x"), None, thread))

    quiet = pool._quiet_when_stopping(got := [], seen.append)
    manager, other = _ExecutorManagerThread(), threading.current_thread()
    quiet(args(manager))  # no signal yet: reported
    got.append(signal.SIGTERM)
    quiet(args(manager))  # stopping: dropped
    quiet(args(other))  # another thread: reported
    assert [a.thread for a in seen] == [manager, other]


def test_the_default_number_of_workers_follows_the_cpus_this_process_may_use(monkeypatch):
    """A fleet review's case: pinned to one CPU (taskset), fit-devices still started two
    workers (os.cpu_count). The default is the process's CPU affinity now."""
    from cascal.pool import MAX_WORKERS, default_workers

    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3}, raising=False)
    assert default_workers() == 1
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(1000)), raising=False)
    assert default_workers() == MAX_WORKERS
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(os, "cpu_count", lambda: 6)
    assert default_workers() == 6
