"""Run the Monte Carlo study on an executor, store trials as they finish, write the outputs.

Work goes to any :mod:`concurrent.futures` executor: local worker processes by default, a
Dask cluster through ``distributed.Client(address).get_executor()``, or the calling
process for one worker. Finished trials are committed to SQLite at once, so an interrupted
study resumes where it stopped with the same command and ends with identical numbers.
"""

from __future__ import annotations

import contextlib
import csv
import io
import json
import logging
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from concurrent.futures import (
    BrokenExecutor,
    CancelledError,
    Executor,
    Future,
)
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import CascalWarning, InputError, WorkerError
from .gp import pin_blas
from .io.atomic import save_figure, together, write_text
from .io.studydb import StudyDB
from .montecarlo import StudyConfig, TrialResult, compiled, run_chunk, run_trial, summarize
from .pool import (
    MAX_WORKERS,
    completed,
    default_workers,
    deferred_signals,
    ignore_interrupts,
    raise_signals,
    shutdown,
    spawn_pool,
    submit_all,
)

__all__ = ["StudyOutcome", "run_study", "trials_table"]

Progress = Callable[[int, int], None]
Notice = Callable[[str], None]


@dataclass(frozen=True, slots=True)
class StudyOutcome:
    """What a finished study wrote and found.

    Attributes:
        folder: Output folder.
        results: Every trial, ordered by index.
        summary: As written to ``summary.json``.
        ran: Trials computed by this call (the rest were resumed from the database).
        stored: Trials in the folder's database, those beyond ``trials`` included.
        span: The ``trials`` whose study covers every stored one (the highest stored
            index plus one: an interrupted run can leave gaps).
        compile_s: Seconds spent compiling the study's code in this process before the
            trials (0 where Numba's cache held it).
    """

    folder: Path
    results: list[TrialResult]
    summary: dict
    ran: int
    stored: int = 0
    span: int = 0
    compile_s: float = 0.0


def run_study(
    out: str | Path,
    *,
    trials: int = 12000,
    config: StudyConfig | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    executor: Executor | None = None,
    chunk: int | None = None,
    progress: Progress | None = None,
    notice: Notice | None = None,
) -> StudyOutcome:
    """Run (or resume) the study in folder ``out`` and write its outputs there.

    Args:
        out: Output folder: ``study.sqlite``, ``trials.csv``, ``summary.json``,
            ``cost_distribution.png`` and ``.svg``.
        trials: Number of trials: trials 0 .. trials-1. A folder can be extended with a
            larger number; a smaller one summarises the first ``trials`` stored.
        config: Seed and fit settings (the folder's identity: other settings are refused).
        workers: Local worker processes (default: the CPUs this process may use; 1 runs
            in this process).
        scheduler: Address of a Dask scheduler to run on instead (needs ``distributed``);
            a :class:`~cascal.errors.CascalWarning` says where it has no workers yet.
        executor: Any executor to run on instead (takes precedence).
        chunk: Trials per task (default: about 8 tasks per worker, at most 50 trials).
        progress: Called as ``progress(done, total)`` after every finished task.
        notice: Called with a line of text before long one-off work: compiling the
            study's code where Numba's cache lacks it (about 55 s on a first run). Local
            runs compile it here, once, before the workers start (they load it from the
            cache); the workers of a cluster compile it on their machines.

    Ctrl-C stops the workers and raises KeyboardInterrupt (the trials stored stay). So
    does SIGTERM where a handler of :mod:`cascal.pool` raises
    :class:`~cascal.pool.Terminated` for it (the ``cascal`` command's); where it has its
    default action, the process ends by it once the workers are stopped.
    """
    config = config or StudyConfig()
    if int(trials) < 1 or (workers is not None and int(workers) < 1):
        raise InputError(f"expected at least 1 trial and 1 worker, got {trials} and {workers}")
    if workers is not None and int(workers) > MAX_WORKERS:
        raise InputError(f"workers: expected at most {MAX_WORKERS} processes, got {workers}")
    if scheduler is not None and executor is None:
        with _quiet_dask_client():
            return _run_study(
                out, trials, config, workers, _connect(scheduler), None, chunk, progress, notice
            )
    return _run_study(out, trials, config, workers, None, executor, chunk, progress, notice)


def _run_study(
    out: str | Path,
    trials: int,
    config: StudyConfig,
    workers: int | None,
    client,
    executor: Executor | None,
    chunk: int | None,
    progress: Progress | None,
    notice: Notice | None,
) -> StudyOutcome:
    """:func:`run_study` on ``client`` (a Dask client it closes), on ``executor``, or on
    local workers."""
    task = run_chunk
    if client is not None:
        client.run(pin_blas)  # workers run tasks on threads: one BLAS limit for all of them
        executor = client.get_executor()
        task = _pinned_chunk  # (and workers that join later pin it with their first task)
    folder = Path(out)
    try:
        db = StudyDB(folder, config.as_dict())
    except BaseException:
        if client is not None:
            client.close()
        raise
    try:
        before = db.results()  # every stored record checked before any work (a review: a
        # damaged one had been found after the pending trials were computed)
        pending = sorted(set(range(trials)) - {r.index for r in before})
        compile_s = 0.0
        if pending and client is None and executor is None:
            compile_s = _compile_here(config, pending[0], notice)
        if pending:
            _check_same_numbers(config, before[0] if before else None, folder)
        n_workers = workers or default_workers()
        size = chunk or max(1, min(50, len(pending) // (8 * n_workers) or 1))
        chunks = [pending[i : i + size] for i in range(0, len(pending), size)]
        done = trials - len(pending)
        if len(pending) >= _PRELOAD:  # the outputs' imports while the workers compute
            # (not a daemon: the interpreter waits for it at exit; a daemon thread frozen
            # inside an import by an early Ctrl-C could hang the exit, which a CI run saw)
            threading.Thread(target=_preload, name="preload").start()
        if progress:
            progress(done, trials)
        computed: dict[int, TrialResult] = {}
        try:
            for results in _execute(config, chunks, executor, n_workers, task):
                db.add(results)
                computed.update((r.index, r) for r in results)
                done += len(results)
                if progress:
                    progress(done, trials)
        except WorkerError as exc:
            raise WorkerError(
                f"{exc}; {done} of {trials} trials are stored in {folder}: run the same "
                "command again to resume"
            ) from None
        # every stored trial: those read at the start and those stored since (the same
        # numbers as reading them back, 0.3 s for 12 000; a stored index is kept)
        computed.update((r.index, r) for r in before)
        stored = [computed[i] for i in sorted(computed)]
        results = [r for r in stored if r.index < trials]
        if client is not None:
            client.close()  # disconnect only: the cluster belongs to the user
            client = None
        with deferred_signals():  # a second or two: the four outputs, then the signal
            summary = _write_outputs(folder, results, config)
    finally:  # the folder's lock is held until its outputs are written
        db.close()
        if client is not None:
            client.close()
    span = max((r.index for r in stored), default=-1) + 1
    return StudyOutcome(folder, results, summary, len(pending), len(stored), span, compile_s)


def _compile_here(config: StudyConfig, index: int, notice: Notice | None) -> float:
    """Compile the study's code in this process by running trial ``index`` where Numba's
    cache lacks it, so that local workers load it instead of each compiling it; the
    seconds that took (0 where it was cached)."""
    if compiled(config):
        return 0.0
    if notice:
        notice(
            "Compiling the study's code for this machine (the first run after installing: "
            "about a minute; it is cached for later runs)"
        )
    t0 = time.perf_counter()
    run_trial(config, index)  # (its result is computed again with the others)
    seconds = time.perf_counter() - t0
    if not compiled(config):
        warnings.warn(
            "Numba's cache does not hold the study's code after compiling it (its folder, "
            "__pycache__ beside cascal or NUMBA_CACHE_DIR, is not kept?): each worker "
            "compiles it again, on every run; set NUMBA_CACHE_DIR to a writable folder",
            CascalWarning,
            stacklevel=4,
        )
    return seconds


#: Pending trials from which the outputs' modules are imported during the run.
_PRELOAD = 500


def _preload() -> None:
    """Import what the outputs need (SciPy's statistics, matplotlib: about 1 s)."""
    with contextlib.suppress(Exception):
        import scipy.stats  # noqa: F401

        from . import plots  # noqa: F401


def _write_outputs(folder: Path, results: list[TrialResult], config: StudyConfig) -> dict:
    """Write trials.csv, summary.json and the figure; returns the summary."""
    summary = summarize({m: np.array([r.cost[m] for r in results]) for m in config.methods})
    summary["redraws"] = int(sum(r.redraws for r in results))
    summary["seconds_per_trial"] = _mean_seconds(results)
    summary["config"] = config.as_dict()
    _sweep(folder)
    from .plots import plot_cost_distribution

    fig = plot_cost_distribution({m: [r.cost[m] for r in results] for m in config.methods})
    with together():  # a run killed here leaves the last run's four files, or the new ones
        write_text(folder / "trials.csv", trials_table(results, config.methods))
        write_text(folder / "summary.json", json.dumps(summary, indent=2) + "\n")
        save_figure(fig, folder / "cost_distribution.png", dpi=130)
        save_figure(fig, folder / "cost_distribution.svg")
    return summary


def _check_same_numbers(config: StudyConfig, stored: TrialResult | None, folder: Path) -> None:
    """Refuse to add trials to a folder whose first stored trial this cascal computes
    differently (another version): the study would mix two versions' numbers."""
    if stored is None:
        return
    fresh = run_trial(config, stored.index)
    if fresh.cost != stored.cost or fresh.fits != stored.fits or fresh.redraws != stored.redraws:
        m = next((m for m in config.methods if fresh.cost[m] != stored.cost[m]), None)
        what = f"J_{m} {stored.cost[m]!r} there, {fresh.cost[m]!r} now" if m else "its fits"
        raise InputError(
            f"{folder}: its trials were computed by a cascal that gives other numbers (trial "
            f"{stored.index}: {what}); adding trials would mix the two: choose another --out "
            "folder, or remove this one to start again"
        )


#: Outputs of a study folder, each written to a temporary file and renamed.
OUTPUTS = ("trials.csv", "summary.json", "cost_distribution.png", "cost_distribution.svg")


def _sweep(folder: Path) -> None:
    """Remove the temporary files of outputs that a killed run left (over a minute old)."""
    now = time.time()
    for name in OUTPUTS:
        for tmp in folder.glob(f".{name}.*.tmp"):
            try:
                if now - tmp.stat().st_mtime > 60.0:
                    tmp.unlink()
            except OSError:
                pass


def _start_worker(parent: int) -> None:
    """A local worker: BLAS on one thread, Ctrl-C left to the command, and an end of its
    own when ``parent`` does (a killed study leaves no workers holding its output pipes
    open)."""
    ignore_interrupts()
    pin_blas()

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _pinned_chunk(config: StudyConfig, indices: list[int]) -> list[TrialResult]:
    """:func:`run_chunk` in a Dask worker, its BLAS pinned to one thread first (a no-op
    where :func:`pin_blas` ran): workers may join the cluster after the study started."""
    pin_blas()
    return run_chunk(config, indices)


def _execute(config, chunks, executor, n_workers, task):
    """Yield each chunk's results as it completes, on the chosen executor (``task`` runs
    a chunk there: :func:`run_chunk` or :func:`_pinned_chunk`)."""
    if not chunks:
        return
    if executor is None and n_workers == 1:
        for c in chunks:
            yield run_chunk(config, c)
        return
    pool = None
    if executor is None:
        executor = pool = spawn_pool(n_workers, _start_worker, (os.getpid(),))
    futures: list[Future] = []
    calls = [(config, c) for c in chunks]
    failed = True
    with deferred_signals() as got:  # Ctrl-C and SIGTERM between waits, not inside one
        try:
            try:
                if pool is not None:
                    futures = submit_all(pool, run_chunk, calls)
                else:
                    futures = [executor.submit(task, *call) for call in calls]
                for fut in completed(futures, got):
                    yield _result(fut)
            except Exception:  # a signal that struck the workers too (a process group's)
                raise_signals(got)  # ends the command as that signal, not as their failure
                raise
            failed = False
        finally:
            for f in futures:
                f.cancel()
            if pool is not None:  # interrupted: the chunks under way run again on resuming
                shutdown(pool, wait_for_tasks=not failed, interrupted=failed)


def _result(fut: Future) -> list[TrialResult]:
    """A chunk's results; a lost worker or cluster is a WorkerError."""
    try:
        return fut.result()
    except (CancelledError, BrokenExecutor) as exc:  # a worker killed, a lost cluster
        raise WorkerError(f"lost the workers ({_named(exc)})") from None
    except Exception as exc:
        if type(exc).__module__.split(".")[0] != "distributed":
            raise
        raise WorkerError(f"the Dask cluster failed ({_named(exc)})") from None


def _named(exc: BaseException) -> str:
    """``Type: message``, or the type alone where the message is empty."""
    return f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__


#: Seconds a Dask scheduler has to answer.
CONNECT_SECONDS = 10.0


def _connect(address: str):
    """A Dask client of the scheduler at ``address``; a bad address is an InputError, and
    so is one where nothing answers Dask's handshake within :data:`CONNECT_SECONDS`."""
    try:
        from distributed import Client
    except ImportError:
        raise InputError(
            f"--scheduler {address}: needs Dask's distributed package, which is not installed: "
            "pip install 'cascal[dask]'"
        ) from None
    try:
        _handshake(address, CONNECT_SECONDS)
        client = Client(address, timeout=f"{CONNECT_SECONDS:g}s")
    except (OSError, ValueError, TimeoutError, TypeError) as exc:  # TypeError: tls://, ucx://
        why = f"{exc}" if str(exc) else f"no answer within {CONNECT_SECONDS:g} s"
        if isinstance(exc, TimeoutError) and address.rstrip("/").endswith(":8787"):
            why += "; 8787 is the dashboard's port, the scheduler's is 8786 by default"
        raise InputError(f"--scheduler {address}: cannot reach a Dask scheduler ({why})") from None
    if not client.scheduler_info().get("workers"):  # (a leftover: it waited with no word)
        warnings.warn(  # (not refused: an adaptive cluster starts workers once work comes)
            f"--scheduler {address}: the scheduler has no workers yet; the study waits for "
            f"them (start some with `dask worker {address}`, or stop with Ctrl-C)",
            CascalWarning,
            stacklevel=3,
        )
    return client


@contextlib.contextmanager
def _quiet_dask_client() -> Iterator[None]:
    """Dask's client logger held to critical messages while a study runs on a cluster (a
    lost cluster is the study's one line, not also Dask's log), then restored: a review
    found it set for the rest of the process."""
    try:
        import distributed  # noqa: F401  (its import configures the logger: set it after)
    except ImportError:  # (_connect names what is missing)
        yield
        return
    log = logging.getLogger("distributed.client")
    level = log.level
    log.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        log.setLevel(level)


def _handshake(address: str, seconds: float) -> None:
    """Open and close one Dask connection to ``address`` within ``seconds``: a server that
    takes the connection but never answers (a dashboard's HTTP port) had kept the
    client waiting with no end, its own timeout notwithstanding. TimeoutError if not."""
    import asyncio

    from distributed.comm import connect

    async def probe() -> None:
        comm = await asyncio.wait_for(connect(address, timeout=seconds), seconds)
        await comm.close()

    asyncio.run(probe())


def _mean_seconds(results: list[TrialResult]) -> dict[str, float]:
    keys = sorted({k for r in results for k in r.seconds})
    return {k: float(np.mean([r.seconds.get(k, 0.0) for r in results])) for k in keys}


def trials_table(results: list[TrialResult], methods) -> str:
    """CSV text: one row per trial with J per method, redraws, fits and timings."""
    fit_keys = sorted({f"{s}.{k}" for r in results for s, d in r.fits.items() for k in d})
    sec_keys = sorted({k for r in results for k in r.seconds})
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(
        [
            "index",
            *(f"J_{m}" for m in methods),
            "redraws",
            *fit_keys,
            *(f"seconds.{k}" for k in sec_keys),
        ]
    )
    split = [k.split(".", 1) for k in fit_keys]
    for r in results:
        fits = [r.fits.get(stage, {}).get(name, "") for stage, name in split]
        w.writerow(
            [
                r.index,
                *(repr(r.cost[m]) for m in methods),
                r.redraws,
                *(repr(v) if v != "" else "" for v in fits),
                *(f"{r.seconds.get(k, 0.0):.6g}" for k in sec_keys),
            ]
        )
    return buf.getvalue()
