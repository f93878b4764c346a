"""The Monte Carlo study runner: determinism across workers, resume, Dask, outputs."""

from __future__ import annotations

import json
import os
import re
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from concurrent.futures import Executor, Future
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest
from scipy.stats import wilcoxon

from cascal.errors import InputError
from cascal.montecarlo import StudyConfig, run_trial, summarize, trial_rng
from cascal.study import run_study
from utils import stored_trials

CONFIG = StudyConfig(seed=7, n_restarts=2)


def _costs(outcome):
    return [(r.index, r.cost) for r in outcome.results]


def test_trial_depends_on_seed_and_index_only():
    a = trial_rng(3, 5).standard_normal(4)
    b = trial_rng(3, 5).standard_normal(4)
    c = trial_rng(3, 6).standard_normal(4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    r1, r2 = run_trial(CONFIG, 2), run_trial(CONFIG, 2)
    assert r1.cost == r2.cost and r1.fits == r2.fits


def test_same_numbers_with_one_and_two_workers(tmp_path):
    one = run_study(tmp_path / "one", trials=6, config=CONFIG, workers=1)
    two = run_study(tmp_path / "two", trials=6, config=CONFIG, workers=2, chunk=1)
    assert _costs(one) == _costs(two)  # bit-identical floats
    assert [r.index for r in one.results] == list(range(6))


def test_interrupted_study_resumes_to_identical_numbers(tmp_path):
    full = run_study(tmp_path / "full", trials=5, config=CONFIG, workers=1)

    def stop_after_two(done, total):
        if done >= 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_study(
            tmp_path / "cut", trials=5, config=CONFIG, workers=1, chunk=1, progress=stop_after_two
        )
    resumed = run_study(tmp_path / "cut", trials=5, config=CONFIG, workers=1)
    assert resumed.ran == 3  # the two stored trials are not run again
    assert _costs(resumed) == _costs(full)
    assert resumed.summary["methods"] == full.summary["methods"]


def test_folder_with_other_configuration_is_refused(tmp_path):
    run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    with pytest.raises(InputError, match="holds a study with configuration"):
        run_study(tmp_path, trials=2, config=StudyConfig(seed=8, n_restarts=2), workers=1)


def _sqlite(path, *statements):
    con = sqlite3.connect(path)
    with con:
        for sql in statements:
            con.execute(sql)
    con.close()


def _study_then(*statements):
    """A damage: edit a finished two-trial study's database with SQL statements."""

    def damage(db):
        run_study(db.parent, trials=2, config=CONFIG, workers=1)
        _sqlite(db, *statements)

    return damage


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (lambda db: db.write_bytes(b"garbage" * 100), "not a readable cascal study database"),
        (lambda db: _sqlite(db, "CREATE TABLE other (a)"), "holds the tables ['other']"),
        (
            _study_then("UPDATE meta SET value='{oops' WHERE key='config'"),
            "unreadable configuration",
        ),
        (
            _study_then("UPDATE meta SET value='2' WHERE key='schema'"),
            "schema '2'; this cascal reads schema 1",
        ),
        (_study_then("ALTER TABLE trials ADD COLUMN extra"), "has trial columns"),
        (_study_then("UPDATE trials SET fits='[1' WHERE idx=1"), "unreadable record of trial 1"),
        (_study_then("UPDATE trials SET redraws='abc' WHERE idx=1"), "record of trial 1"),
        (_study_then("""UPDATE trials SET fits='{"stage0": [1]}' WHERE idx=0"""), "of trial 0"),
        (_study_then("""UPDATE trials SET seconds='{"a": "slow"}' WHERE idx=1"""), "of trial 1"),
        (_study_then("UPDATE trials SET j_bayes=9e999 WHERE idx=0"), "record of trial 0"),
        (_study_then("UPDATE trials SET idx=-5 WHERE idx=0"), "record of trial -5"),
    ],
    ids=[
        "not_sqlite",
        "foreign_tables",
        "bad_config",
        "newer_schema",
        "columns",
        "bad_json",
        "bad_redraws",
        "bad_fits",
        "bad_seconds",
        "infinite_J",
        "negative_index",
    ],
)
def test_damaged_database_is_refused_untouched(tmp_path, damage, words):
    """A study.sqlite that is not, or no longer, a readable study of this schema is refused
    with a message naming it, and nothing is written to it."""
    db = tmp_path / "study.sqlite"
    damage(db)
    before = db.read_bytes()
    with pytest.raises(InputError, match=re.escape(words)) as info:
        run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    assert str(db) in str(info.value)
    assert db.read_bytes() == before


def test_dask_cluster_gives_the_local_numbers(tmp_path):
    distributed = pytest.importorskip("distributed")
    local = run_study(tmp_path / "local", trials=4, config=CONFIG, workers=1)
    with distributed.LocalCluster(
        n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        remote = run_study(
            tmp_path / "dask", trials=4, config=CONFIG, scheduler=cluster.scheduler_address, chunk=1
        )
    assert _costs(remote) == _costs(local)


def test_a_cluster_without_workers_is_named_and_waited_for(tmp_path):
    """A leftover of a review: a scheduler with no workers kept the study waiting without a
    word. It warns now and waits (an adaptive cluster starts workers once work comes): a
    worker joining later runs the trials, with the local numbers. Dask's client logger,
    held to critical messages during the study, is restored after it (it had stayed so for
    the rest of the process)."""
    import logging
    import threading

    from cascal.errors import CascalWarning

    distributed = pytest.importorskip("distributed")
    local = run_study(tmp_path / "local", trials=2, config=CONFIG, workers=1)
    log = logging.getLogger("distributed.client")
    log.setLevel(logging.INFO)
    with distributed.LocalCluster(
        n_workers=0, threads_per_worker=1, processes=False, dashboard_address=None
    ) as cluster:
        late = threading.Timer(1.0, cluster.scale, (1,))
        late.start()
        with pytest.warns(CascalWarning, match=r"the scheduler has no workers yet; the study"):
            remote = run_study(
                tmp_path / "dask", trials=2, config=CONFIG, scheduler=cluster.scheduler_address
            )
        late.join()
    assert _costs(remote) == _costs(local) and remote.ran == 2
    assert log.level == logging.INFO


def test_summary_against_independent_statistics():
    rng = np.random.default_rng(0)
    a = rng.lognormal(0, 1, 200)
    b = a * rng.lognormal(0.3, 0.2, 200)
    s = summarize({"a": a, "b": b})
    assert s["n_trials"] == 200
    assert s["methods"]["a"]["median"] == pytest.approx(np.percentile(a, 50), rel=1e-12)
    assert s["methods"]["b"]["q90"] == pytest.approx(np.percentile(b, 90), rel=1e-12)
    assert s["methods"]["a"]["mean"] == pytest.approx(a.mean(), rel=1e-12)
    pair = s["pairs"]["a vs b"]
    assert pair["fraction_a_better"] == pytest.approx(np.count_nonzero(a < b) / 200)
    assert pair["wilcoxon_p"] == pytest.approx(wilcoxon(a - b).pvalue, rel=1e-12)


def test_cli_study_writes_outputs(tmp_path):
    out = tmp_path / "study"
    cmd = [
        sys.executable,
        "-m",
        "cascal.cli",
        "study",
        "--trials",
        "3",
        "--workers",
        "1",
        "--restarts",
        "2",
        "--out",
        str(out),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert "median J" in done.stdout
    rows = (out / "trials.csv").read_text().splitlines()
    assert rows[0].startswith("index,J_bayes,J_homoscedastic,J_lut,redraws")
    assert len(rows) == 4
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["methods"]) == {"bayes", "homoscedastic", "lut"}
    assert (out / "cost_distribution.png").stat().st_size > 10_000
    assert (out / "cost_distribution.svg").read_text().lstrip().startswith("<?xml")
    again = subprocess.run(
        [*cmd[:-4], "--restarts", "3", "--out", str(out)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert again.returncode == 2 and "Traceback" not in again.stderr


def test_progress_prints_sparse_plain_lines_when_not_a_terminal():
    import io

    from cascal.cli_study import Progress

    stream = io.StringIO()
    p = Progress(stream=stream, every_s=3600.0)
    for done in range(0, 101, 10):
        p(done, 100)
    p.close()
    lines = stream.getvalue().splitlines()
    # the first call only starts the clock; the rest wait an hour, except the last
    assert len(lines) == 1
    assert lines[0].startswith("100/100 trials (100 %)") and "trials/s" in lines[0]
    assert "ETA" in lines[0]


def _read_pty(master: int, until: str = "10/10", seconds: float = 5.0) -> str:
    """What a pseudo-terminal's other end wrote, read until ``until`` shows (one read can
    return a line at a time: CI once saw the first of two lines only)."""
    import select

    out, deadline = "", time.monotonic() + seconds
    while until not in out and time.monotonic() < deadline:
        if select.select([master], [], [], 0.1)[0]:
            out += os.read(master, 65536).decode()
    return out


@pytest.mark.parametrize("columns", [100, 0])
def test_progress_draws_a_bar_with_rate_on_a_terminal(columns):
    """On a terminal: a bar with the rate and ETA. A review's case: a pseudo-terminal whose
    size was never set (0 columns, as in some CI and containers) showed nothing at all,
    tqdm drawing no bar of no width; it now gets the plain lines."""
    import fcntl
    import os
    import pty
    import struct
    import termios

    from cascal.cli_study import Progress

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    with os.fdopen(slave, "w") as stream:
        p = Progress(stream=stream, every_s=0.0)
        for done in (0, 5, 10):
            p(done, 10)
        assert p.bar is None  # closed at the last trial: its rate is not the outputs' (a review)
        p.close()
        stream.flush()
        out = _read_pty(master)
    os.close(master)
    if columns:
        assert "10/10" in out and "trial/s" in out
    else:
        assert "10/10 trials (100 %)" in out and "trials/s, ETA" in out, out


def test_a_study_grows_without_rerunning_stored_trials(tmp_path):
    small = run_study(tmp_path, trials=3, config=CONFIG, workers=1)
    grown = run_study(tmp_path, trials=5, config=CONFIG, workers=1)
    assert grown.ran == 2
    assert _costs(grown)[:3] == _costs(small)
    assert _costs(grown) == _costs(
        run_study(tmp_path / "direct", trials=5, config=CONFIG, workers=1)
    )
    head = run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    assert head.ran == 0 and _costs(head) == _costs(small)[:2]


def test_a_folder_of_another_versions_numbers_is_not_extended(tmp_path):
    """Trials stored by a cascal that computes other numbers (here: trial 0's J of the
    lookup tables one part in 1e12 off) are not mixed with this one's; summarising what is
    stored still works."""
    run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    db = tmp_path / "study.sqlite"
    _sqlite(db, "UPDATE trials SET j_lut = j_lut * (1 + 1e-12) WHERE idx=0")
    before = db.read_bytes()
    with pytest.raises(InputError, match=r"trial 0: J_lut .* there, .* now\); adding trials"):
        run_study(tmp_path, trials=3, config=CONFIG, workers=1)
    assert db.read_bytes() == before
    assert run_study(tmp_path, trials=2, config=CONFIG, workers=1).ran == 0


def test_bad_counts_and_scheduler_are_input_errors(tmp_path):
    with pytest.raises(InputError, match="at least 1 trial"):
        run_study(tmp_path / "a", trials=0, config=CONFIG, workers=1)
    with pytest.raises(InputError, match="at least 1 trial and 1 worker"):
        run_study(tmp_path / "b", trials=2, config=CONFIG, workers=0)
    pytest.importorskip("distributed")
    with pytest.raises(InputError, match="cannot reach a Dask scheduler"):
        run_study(tmp_path / "c", trials=2, config=CONFIG, scheduler="notanaddress")
    assert not (tmp_path / "c").exists()  # nothing written before the cluster answered


def test_a_scheduler_address_dask_cannot_use_is_an_input_error(tmp_path, monkeypatch):
    """A review's cases: ``tls://`` (no SSL context given) and ``ucx://`` (no UCX) made
    Dask's Client raise TypeError, which ended in a traceback. (Dask's own Client is
    replaced here: a real failed start can leave its IO loop slow to start the next.)"""
    distributed = pytest.importorskip("distributed")

    def refuse(address, timeout):
        raise TypeError("TLS expects a ssl_context argument of type ssl.SSLContext")

    monkeypatch.setattr(distributed, "Client", refuse)
    with pytest.raises(InputError, match=r"--scheduler tls://h:1: cannot reach a Dask sch"):
        run_study(tmp_path / "c", trials=2, config=CONFIG, scheduler="tls://h:1")
    assert not (tmp_path / "c").exists()


def test_a_server_that_never_answers_is_no_scheduler(tmp_path, monkeypatch):
    """A review's case: ``--scheduler`` at the dashboard's port (8787, an HTTP server)
    took the connection and never answered Dask's handshake; the command waited with no
    end, and no word. Now it is refused once the handshake has had its seconds."""
    import socket

    pytest.importorskip("distributed")
    from cascal import study

    server = socket.create_server(("127.0.0.1", 0))  # accepts (the backlog), never answers
    port = server.getsockname()[1]
    monkeypatch.setattr(study, "CONNECT_SECONDS", 1.0)
    t0 = time.perf_counter()
    try:
        with pytest.raises(InputError, match=r"cannot reach a Dask scheduler \(no answer within"):
            run_study(tmp_path / "s", trials=2, config=CONFIG, scheduler=f"tcp://127.0.0.1:{port}")
    finally:
        server.close()
    assert time.perf_counter() - t0 < 30.0 and not (tmp_path / "s").exists()


def test_pinned_blas_stays_single_threaded_on_every_thread(monkeypatch):
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_info

    from cascal import gp
    from cascal.gp import pin_blas, single_threaded_blas

    monkeypatch.setattr(gp, "_PINNED", [])  # this test process is pinned only for this test

    def blas_threads() -> set[int]:
        return {i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"}

    def task(_) -> set[int]:
        with single_threaded_blas():  # entering and leaving on several threads at once
            pass
        return blas_threads()

    with ThreadPoolExecutor(1) as pinning:
        pinning.submit(pin_blas).result()
        with ThreadPoolExecutor(3) as workers:
            seen = set().union(*workers.map(task, range(12)))
        assert seen <= {1} and blas_threads() <= {1}


def test_a_run_killed_while_creating_the_database_leaves_no_half(tmp_path, monkeypatch):
    """A review's case: CREATE TABLE committed on its own, so a run killed between the two
    tables left a folder that every later run refused (schema None)."""
    from cascal.io.studydb import StudyDB

    def half(self, config):
        self.con.execute("CREATE TABLE meta (key TEXT PRIMARY KEY, value TEXT)")
        raise KeyboardInterrupt  # killed here

    with monkeypatch.context() as m:
        m.setattr(StudyDB, "_check_or_create", half)
        with pytest.raises(KeyboardInterrupt):
            StudyDB(tmp_path, CONFIG.as_dict())
    again = run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    assert again.ran == 2


def test_a_full_disk_is_no_bad_database(tmp_path):
    """A review's case: 'database or disk is full' was reported as an unreadable study
    database (exit 2); it is a write that failed, as for the other outputs."""
    from cascal.io.studydb import StudyDB

    db = StudyDB(tmp_path, CONFIG.as_dict())
    db.close()
    full = sqlite3.OperationalError("database or disk is full")
    assert isinstance(db._unreadable(full), OSError)
    assert f"cannot write {db.path}: database or disk is full" in str(db._unreadable(full))
    assert isinstance(db._unreadable(sqlite3.DatabaseError("file is not a database")), InputError)


def test_stale_temporaries_of_a_killed_run_are_swept(tmp_path):
    import os
    import time

    run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    stale, fresh = tmp_path / ".trials.csv.abc123.tmp", tmp_path / ".summary.json.new.tmp"
    for p in (stale, fresh):
        p.write_text("half")
    old = time.time() - 3600
    os.utime(stale, (old, old))
    run_study(tmp_path, trials=2, config=CONFIG, workers=1)
    assert not stale.exists() and fresh.exists()  # a fresh one may be another run's


def test_workers_end_when_the_study_process_is_killed(tmp_path):
    """A review's case: workers of a SIGKILLed study lived on, holding its output pipes."""
    import os
    import time

    code = (
        "import os, multiprocessing\n"
        "from concurrent.futures import ProcessPoolExecutor\n"
        "from cascal.study import _start_worker\n"
        "if __name__ == '__main__':\n"
        "    ctx = multiprocessing.get_context('spawn')\n"
        "    ex = ProcessPoolExecutor(1, mp_context=ctx, initializer=_start_worker,\n"
        "                             initargs=(os.getpid(),))\n"
        "    print(ex.submit(os.getpid).result(), flush=True)\n"
        "    os._exit(0)  # as if killed: no shutdown\n"
    )
    script = tmp_path / "parent.py"
    script.write_text(code)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=60)
    child = int(out.stdout.strip())

    def alive(pid: int) -> bool:  # (a zombie has ended: whether it is reaped is init's)
        try:
            with open(f"/proc/{pid}/stat") as fh:
                return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
        except FileNotFoundError:
            return False
        except OSError:  # no /proc: ask the kernel
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                return False
            return True

    for _ in range(200):  # it notices within half a second; allow 20 s on a busy machine
        if not alive(child):
            break
        time.sleep(0.1)
    else:
        os.kill(child, 9)
        pytest.fail(f"worker {child} outlived its parent")


def test_a_folder_in_use_by_another_run_is_refused(tmp_path):
    """A review's case: two runs open on one folder both computed its pending trials. Now
    the second is refused while the first holds the folder, and runs once it has ended."""
    from cascal.io.studydb import StudyDB

    first = StudyDB(tmp_path, CONFIG.as_dict())
    try:
        with pytest.raises(InputError, match="in use by another cascal study run"):
            run_study(tmp_path, trials=2, config=CONFIG, workers=1)
        assert first.done() == set()  # the refused run stored nothing
    finally:
        first.close()
    assert run_study(tmp_path, trials=2, config=CONFIG, workers=1).ran == 2


def test_cli_study_on_a_folder_in_use_exits_2(tmp_path):
    from cascal.io.studydb import StudyDB

    held = StudyDB(tmp_path / "s", CONFIG.as_dict())
    try:
        p = subprocess.run(
            [
                sys.executable,
                "-m",
                "cascal.cli",
                "study",
                "--trials",
                "1",
                "--out",
                str(tmp_path / "s"),
            ],
            capture_output=True,
            text=True,
        )
    finally:
        held.close()
    assert p.returncode == 2, p.stderr
    assert "in use by another cascal study run" in p.stderr and "Traceback" not in p.stderr


def test_the_folder_stays_locked_while_the_outputs_are_written(tmp_path, monkeypatch):
    """A diff review's case: the lock ended when the trials were stored, so a second run
    started while the first wrote trials.csv, and the folder ended with one run's summary
    and the other's figure."""
    from cascal import study
    from cascal.io.studydb import StudyDB

    seen = []
    write = study._write_outputs

    def writing(folder, results, config):
        with pytest.raises(InputError, match="in use by another cascal study run"):
            StudyDB(folder, config.as_dict())
        seen.append(len(results))
        return write(folder, results, config)

    monkeypatch.setattr(study, "_write_outputs", writing)
    assert run_study(tmp_path, trials=2, config=CONFIG, workers=1).ran == 2 and seen == [2]
    StudyDB(tmp_path, CONFIG.as_dict()).close()  # free once the run has ended


class _Breaking(Executor):
    """Runs the first ``k`` tasks at once, then fails the rest as a killed worker would."""

    def __init__(self, k: int) -> None:
        self.k = k

    def submit(self, fn, /, *args, **kwargs):
        fut: Future = Future()
        if self.k > 0:
            self.k -= 1
            fut.set_result(fn(*args, **kwargs))
        else:  # fails later: after the finished ones have been stored
            err = BrokenProcessPool("a process was terminated abruptly")
            threading.Timer(0.2, fut.set_exception, (err,)).start()
        return fut


def test_lost_workers_are_named_and_the_study_resumes(tmp_path):
    """A review's cases: a local worker killed (BrokenProcessPool) or the Dask scheduler
    lost (CancelledError) ended in a traceback. Now a WorkerError (the CLI: one line, exit
    1) says how many trials are stored; the same command resumes to the same numbers."""
    from cascal.errors import WorkerError

    words = r"lost the workers \(BrokenProcessPool: .*; 2 of 4 trials are stored in .*: run"
    with pytest.raises(WorkerError, match=words):
        run_study(tmp_path, trials=4, config=CONFIG, executor=_Breaking(1), chunk=2)
    resumed = run_study(tmp_path, trials=4, config=CONFIG, workers=1)
    assert resumed.ran == 2
    direct = run_study(tmp_path / "direct", trials=4, config=CONFIG, workers=1)
    assert _costs(resumed) == _costs(direct)


def test_cli_study_names_a_shrunk_summary_and_a_dangling_link(tmp_path):
    """A folder summarised with fewer trials than it holds says so; an --out that is a
    link to nothing is refused (it read "File exists", exit 1)."""
    out = tmp_path / "study"
    cmd = [sys.executable, "-m", "cascal.cli", "study", "--workers", "1", "--out", str(out)]
    for n in ("3", "2"):
        done = subprocess.run([*cmd, "--trials", n], capture_output=True, text=True, check=False)
        assert done.returncode == 0, done.stderr
    assert "The folder holds 3 trials; its outputs now cover the first 2" in done.stdout
    assert "(run with --trials 3 for all)" in done.stdout
    with sqlite3.connect(out / "study.sqlite") as con:  # a gap, as an interrupted run leaves
        con.execute("DELETE FROM trials WHERE idx = 1")
    done = subprocess.run([*cmd, "--trials", "1"], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert "holds 2 trials" in done.stdout and "(run with --trials 3 for all)" in done.stdout
    link = tmp_path / "dangling"
    link.symlink_to(tmp_path / "nowhere")
    cmd[-1] = str(link)
    done = subprocess.run([*cmd, "--trials", "1"], capture_output=True, text=True, check=False)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert f"--out {link}: a link to {tmp_path / 'nowhere'}, which does not exist" in done.stderr


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
@pytest.mark.parametrize(
    ("signals", "status", "word"),
    [(("SIGINT", "SIGINT"), 130, "interrupted"), (("SIGTERM",), 143, "terminated")],
    ids=["two_ctrl_c_together", "sigterm"],
)
def test_cli_study_stopped_by_signals_says_so_and_resumes(tmp_path, signals, status, word):
    """A review's cases: two Ctrl-C back to back (a terminal sends them to the whole
    process group) ended about one time in three with a traceback from ``as_completed``
    and exit 1; SIGTERM ended with multiprocessing's warning of leaked semaphores and no
    word of the stored trials. Both now stop the workers and say so, and the same command
    then finishes the study."""
    out = tmp_path / "s"
    cmd = [sys.executable, "-m", "cascal.cli", "study", "--trials", "2000", "--workers", "2"]
    cmd += ["--restarts", "2", "--seed", "7", "--out", str(out)]
    p = subprocess.Popen(
        cmd,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
    )
    deadline = time.monotonic() + 120
    while stored_trials(out / "study.sqlite") < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    for name in signals:
        os.killpg(p.pid, getattr(signal, name))
    _, err = p.communicate(timeout=60)
    assert p.returncode == status, err
    assert "Traceback" not in err and "leaked" not in err
    assert f"cascal study: {word} (the trials stored in {out} stay" in err
    stored = stored_trials(out / "study.sqlite")
    assert 1 <= stored < 2000
    resumed = run_study(out, trials=stored + 3, config=CONFIG, workers=1)
    assert resumed.ran >= 3 and [r.index for r in resumed.results] == list(range(stored + 3))


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")
def test_sigterm_while_the_outputs_are_written_lets_them_finish(tmp_path, monkeypatch):
    """SIGTERM while the four outputs were written ended the process there, silently:
    now they are finished first (a second or two), then the signal ends the study."""
    from cascal import study
    from cascal.pool import Terminated, raise_terminated

    write = study._write_outputs

    def terminated_meanwhile(*args):
        os.kill(os.getpid(), signal.SIGTERM)
        return write(*args)

    monkeypatch.setattr(study, "_write_outputs", terminated_meanwhile)
    signal.signal(signal.SIGTERM, raise_terminated)  # (the command's handler)
    try:
        with pytest.raises(Terminated):
            run_study(tmp_path, trials=2, config=CONFIG, workers=1)
        assert signal.getsignal(signal.SIGTERM) is raise_terminated
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    assert len((tmp_path / "trials.csv").read_text().splitlines()) == 3
    assert (tmp_path / "cost_distribution.svg").exists()


def test_a_damaged_record_is_refused_before_pending_trials_run(tmp_path, monkeypatch):
    """A review's case: a damaged record of a trial other than the first was found only
    after the pending trials had been computed and stored (hours, on an extension), and
    the message then said to abandon the folder. Every stored record is read first now."""
    from cascal import study

    run_study(tmp_path, trials=3, config=CONFIG, workers=1)
    db = tmp_path / "study.sqlite"
    _sqlite(db, "UPDATE trials SET fits='[1' WHERE idx=1", "DELETE FROM trials WHERE idx=2")
    before = db.read_bytes()

    def no_work(*args):
        raise AssertionError("a trial ran")

    monkeypatch.setattr(study, "run_chunk", no_work)
    monkeypatch.setattr(study, "run_trial", no_work)
    with pytest.raises(InputError, match=r"unreadable record of trial 1"):
        run_study(tmp_path, trials=4, config=CONFIG, workers=1)
    assert db.read_bytes() == before


def test_a_study_database_that_is_no_regular_file_is_refused(tmp_path):
    """A review's case: study.sqlite as a link to /dev/null, or a named pipe, was called a
    disk I/O error (status 1); it is no study database (status 2)."""
    (tmp_path / "a").mkdir()
    os.mkfifo(tmp_path / "a" / "study.sqlite")
    with pytest.raises(InputError, match=r"study.sqlite is not a regular file"):
        run_study(tmp_path / "a", trials=2, config=CONFIG, workers=1)
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "study.sqlite").symlink_to(os.devnull)
    with pytest.raises(InputError, match=r"study.sqlite is not a regular file"):
        run_study(tmp_path / "b", trials=2, config=CONFIG, workers=1)


def test_worker_counts_beyond_the_cap_and_a_missing_dask_are_input_errors(tmp_path, monkeypatch):
    """A review's cases: --workers 3000000000 crashed inside multiprocessing with a
    traceback after making the folder, and 100000 started a process per task; --scheduler
    without Dask's distributed package installed ended in ModuleNotFoundError."""
    from cascal.pool import MAX_WORKERS

    with pytest.raises(InputError, match=f"at most {MAX_WORKERS} processes, got 3000000000"):
        run_study(tmp_path / "w", trials=2, config=CONFIG, workers=3_000_000_000)
    assert not (tmp_path / "w").exists()
    res = subprocess.run(
        [sys.executable, "-m", "cascal.cli", "study", "--trials", "2", "--workers", "100000",
         "--out", str(tmp_path / "x")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert res.returncode == 2 and "--workers: expected at most 256 processes" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "x").exists()
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(InputError, match=r"needs Dask's distributed package.*cascal\[dask\]"):
        run_study(tmp_path / "d", trials=2, config=CONFIG, scheduler="tcp://127.0.0.1:8786")
    assert not (tmp_path / "d").exists()


def test_dasks_client_log_is_silenced_after_dask_is_imported():
    """A review's case: a lost cluster printed Dask's ERROR line before the study's own
    one line: the command had set that logger's level before importing Dask, whose import
    set it again. In a fresh process (Dask not yet imported), the context a study on a
    cluster runs in (``run_study`` enters it for ``scheduler=``) sets it after the import,
    and restores Dask's own level when it ends (a study through it:
    ``test_a_cluster_without_workers_is_named_and_waited_for``)."""
    pytest.importorskip("distributed")
    script = (
        "import logging\n"
        "from cascal import study\n"
        "log = logging.getLogger('distributed.client')\n"
        "with study._quiet_dask_client():\n"
        "    print(log.level)\n"
        "print(log.level)\n"
    )
    cmd = [sys.executable, "-c", script]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.split() == ["50", "30"]  # CRITICAL, then WARNING as Dask set it


def test_progress_says_eta_unknown_before_a_trial_is_done():
    """A review: with no trial done yet (a cluster without workers), the ETA read "nan s"."""
    import io

    from cascal.cli_study import Progress

    stream = io.StringIO()
    p = Progress(stream=stream, every_s=0.0)
    p(0, 200)
    p(0, 200)
    assert stream.getvalue().strip().endswith("ETA unknown (none done yet)")


def test_compiled_reads_numbas_cache_of_the_study_code(tmp_path):
    """True once a trial has run here (its code cached beside the package); False for an
    empty cache folder, where a process would compile it first."""
    from cascal.montecarlo import compiled

    run_trial(CONFIG, 0)
    assert compiled(CONFIG)
    cold = subprocess.run(
        [sys.executable, "-c", "from cascal.montecarlo import *; print(compiled(StudyConfig()))"],
        env={**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)},
        capture_output=True,
        text=True,
        check=True,
    )
    assert cold.stdout.strip() == "False"


def test_a_cold_cache_is_compiled_once_before_the_trials_and_said(tmp_path, monkeypatch):
    """Where Numba's cache lacks the study's code, the study compiles it in this process
    before its workers start (they then load it instead of each compiling it), says so
    first and reports the seconds apart from the trials; the numbers are the same."""
    import cascal.study

    lines: list[str] = []
    monkeypatch.setattr(cascal.study, "compiled", lambda config: True)
    warm = run_study(tmp_path / "warm", trials=3, config=CONFIG, workers=1, notice=lines.append)
    assert warm.compile_s == 0.0 and lines == []
    checks = iter([False, True])  # cold, then cached by the compiling
    monkeypatch.setattr(cascal.study, "compiled", lambda config: next(checks))
    cold = run_study(tmp_path / "cold", trials=3, config=CONFIG, workers=1, notice=lines.append)
    assert cold.compile_s > 0.0 and len(lines) == 1 and "Compiling the study's code" in lines[0]
    assert _costs(cold) == _costs(warm) and cold.ran == 3
    lines.clear()
    again = run_study(tmp_path / "cold", trials=3, config=CONFIG, workers=1, notice=lines.append)
    assert again.ran == 0 and again.compile_s == 0.0 and lines == []  # nothing pending


def test_a_cache_that_keeps_nothing_is_warned_of(tmp_path, monkeypatch):
    import cascal.study
    from cascal.errors import CascalWarning

    monkeypatch.setattr(cascal.study, "compiled", lambda config: False)
    with pytest.warns(CascalWarning, match="each worker compiles it again"):
        run_study(tmp_path, trials=1, config=CONFIG, workers=1)


def test_the_command_reports_compiling_apart_from_the_study(tmp_path, monkeypatch, capsys):
    import cascal.study
    from cascal.cli import main

    checks = iter([False, True])
    monkeypatch.setattr(cascal.study, "compiled", lambda config: next(checks))
    out = tmp_path / "study"
    assert main(["study", "--trials", "2", "--workers", "1", "--seed", "7", "--out", str(out)]) == 0
    got = capsys.readouterr()
    assert "Compiling the study's code for this machine" in got.err
    assert re.search(r"Before it, compiling the study's code took \d+\.\d s", got.out)
    assert "Study of 2 trials" in got.out


def test_stage_fits_are_the_fits_a_trial_records():
    from cascal.montecarlo import stage_fits
    from cascal.simulation import simulate_trial

    rng = trial_rng(CONFIG.seed, 4)
    trial = simulate_trial(rng)
    gp0, stage_b = stage_fits(CONFIG, trial, int(rng.integers(2**63)))
    fits = run_trial(CONFIG, 4).fits
    assert sorted(stage_b) == ["bayes", "homoscedastic"]
    pairs = [(gp0, "stage0")] + [(stage_b[m], f"{m}/stage1") for m in stage_b]
    for gp, key in pairs:
        assert gp.log_marginal_likelihood == fits[key]["log_marginal_likelihood"]
        assert all(float(v) == fits[key][k] for k, v in gp.hyperparameters.items())
