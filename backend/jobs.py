"""Starting, watching and cancelling job processes (`kgs_backend.worker`).

A job is a registry row (a scene, run or export) with `status` queued → running → done | failed
| cancelled, the `pid` of its process and, on failure, the error. At most `max_jobs` processes
run at once (the machine's cores); the rest wait in a first-in first-out queue whose positions
the API shows. A watcher thread per job waits for the process, records how it ended and starts
the next queued one; at start-up `recover` marks jobs whose process is gone as `interrupted` (a
training run keeps its checkpoints and can be resumed).

Each job process gets its own temporary folder (`jobs/<id>.tmp`, its TMPDIR), removed once the
process has exited however it ended: a library that ends the process on SIGTERM before Python
unwinds (glog, inside SfM) leaves nothing behind.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from kgs_core.threads import cores_to_use, placement_env, placement_off

from .registry import ACTIVE, CANCELLABLE, JobStatus, Workspace, relative_text


def job_process(pid: int | None, job_id: str) -> bool:
    """Whether `pid` is alive and still the worker of job `job_id`: a PID stored before a
    restart may since belong to an unrelated process, which must never be signalled. Where
    /proc is missing the check falls back to `pid_alive`."""
    if not pid_alive(pid):
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except FileNotFoundError:
        return False
    except OSError:
        return True  # no /proc here: only the PID to go by
    return b"kgs_backend.worker" in cmdline and job_id.encode() in cmdline


def pid_alive(pid: int | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, PermissionError):
        return False
    try:  # a zombie child of ours counts as gone
        done, _ = os.waitpid(pid, os.WNOHANG)
        return done == 0
    except ChildProcessError:
        return True


def last_checkpoint(run_dir: Path) -> int | None:
    """The iteration of a run directory's last checkpoint, None without one."""
    its = [int(p.stem.split("_")[-1]) for p in (run_dir / "checkpoints").glob("ckpt_*.pt") if p.stem.split("_")[-1].isdigit()]
    return max(its) if its else None


@dataclass
class QueuedJob:
    table: str
    id: str
    kind: str
    spec: dict
    on_done: object = None


class JobRunner:
    def __init__(self, ws: Workspace, max_jobs: int | None = None):
        self.ws = ws
        self.procs: dict[str, subprocess.Popen] = {}
        self.max_jobs = max_jobs or max(1, cores_to_use())
        self.queue: deque[QueuedJob] = deque()
        self._lock = threading.RLock()
        ws.queue_position = self.position

    def start(self, table: str, id_: str, kind: str, spec: dict, on_done=None) -> None:
        """Runs the job now, or queues it (status `queued`) while `max_jobs` others run."""
        with self._lock:
            if len(self.live()) >= self.max_jobs:
                self.queue.append(QueuedJob(table, id_, kind, spec, on_done))
                self.ws.update(table, id_, status=JobStatus.QUEUED, pid=None, error=None)
                return
            self._launch(QueuedJob(table, id_, kind, spec, on_done))

    def position(self, id_: str) -> int | None:
        """1 for the next job to start, None for a job not in the queue."""
        with self._lock:
            return next((k + 1 for k, job in enumerate(self.queue) if job.id == id_), None)

    def _start_queued(self) -> None:
        with self._lock:
            while self.queue and len(self.live()) < self.max_jobs:
                job = self.queue.popleft()
                row = self.ws.get(job.table, job.id)
                if row is not None and row["status"] == JobStatus.QUEUED:
                    self._launch(job)

    def tmp_dir(self, id_: str) -> Path:
        return self.ws.root / "jobs" / f"{id_}.tmp"

    def _launch(self, job: QueuedJob) -> None:
        table, id_, kind, spec, on_done = job.table, job.id, job.kind, job.spec, job.on_done
        log = open(self.ws.root / "jobs" / f"{id_}.log", "ab")
        tmp = self.tmp_dir(id_)
        tmp.mkdir(exist_ok=True)
        cores = self.share(len(self.live()) + 1)
        # The count is the runner's choice, not the user's: the job's ThreadTuner may change it
        # (unless the server itself was given a fixed count, which its KGS_OMP_FROM_USER says).
        placement = {**placement_env(cores), "KGS_OMP_FROM_USER": os.environ.get("KGS_OMP_FROM_USER", "0")} if cores else {}
        # A job never compiles the C++ rasteriser (the server started with it built).
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "KGS_EXT_BUILD": "0", "TMPDIR": str(tmp), **placement}
        # The job id on the command line is what `job_process` recognises the process by.
        proc = subprocess.Popen(
            [sys.executable, "-m", "kgs_backend.worker", kind, json.dumps(spec), id_],
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            env=env,
        )
        log.close()
        self.procs[id_] = proc
        self.ws.update(table, id_, status=JobStatus.RUNNING, pid=proc.pid, error=None)
        threading.Thread(target=self._watch, args=(table, id_, proc, on_done), daemon=True).start()

    def live(self) -> list[str]:
        return [i for i, p in list(self.procs.items()) if p.poll() is None]

    @staticmethod
    def share(jobs: int) -> int | None:
        """The cores a job starts with when `jobs` run at once: the machine's (or KGS_THREADS)
        divided among them, at least one; None with KGS_THREADS=off (the environment is left
        alone). A training then follows the load (kgs_core.threads.ThreadTuner): it takes the
        cores back when the others end, and gives way to the server's own rendering."""
        if placement_off():
            return None
        return max(1, cores_to_use() // max(1, jobs))

    def _watch(self, table: str, id_: str, proc: subprocess.Popen, on_done) -> None:
        rc = proc.wait()
        shutil.rmtree(self.tmp_dir(id_), ignore_errors=True)
        with self._lock:
            self.procs.pop(id_, None)
        try:
            self._record(table, id_, rc, on_done)
        finally:
            self._start_queued()

    def _record(self, table: str, id_: str, rc: int, on_done) -> None:
        row = self.ws.get(table, id_)
        if row is None:  # deleted meanwhile
            return
        if row["status"] == JobStatus.CANCELLING:
            status, error = JobStatus.CANCELLED, None
        elif rc == 0:
            status, error = JobStatus.DONE, None
        elif rc < 0 and table == "runs" and (kept := last_checkpoint(Path(row["path"]))) is not None:
            # Killed by a signal (the OOM killer, a kill -9): not a failure of the run, which
            # can continue from its last checkpoint (POST /api/runs/{id}/resume).
            status = JobStatus.INTERRUPTED
            error = f"the training process was killed (signal {-rc}); its last checkpoint (iteration {kept}) is kept: resume it"
        else:
            status, error = JobStatus.FAILED, self.last_error(id_) or f"job process exited with code {rc}"
        self.ws.update(table, id_, status=status, error=error, pid=None)
        if on_done:
            on_done(status)

    def last_error(self, id_: str) -> str | None:
        """The last exception line of the job's log (what a user needs first)."""
        path = self.ws.root / "jobs" / f"{id_}.log"
        if not path.is_file():
            return None
        # Paths inside the workspace are told relative to it: the server's own layout is not
        # the client's business.
        lines = [relative_text(ln, self.ws.root) for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
        for ln in reversed(lines):
            if ln and not ln.startswith(" ") and ("Error" in ln or "Exception" in ln):
                return ln[-2000:]
        return lines[-1][-2000:] if lines else None

    def cancel(self, table: str, id_: str) -> bool:
        with self._lock:
            queued = next((job for job in self.queue if job.id == id_), None)
            if queued is not None:  # never started: nothing to stop
                self.queue.remove(queued)
                self.ws.update(table, id_, status=JobStatus.CANCELLED, pid=None)
                return True
        row = self.ws.get(table, id_)
        if row is None or row["status"] not in CANCELLABLE or not job_process(row["pid"], id_):
            return False
        self.ws.update(table, id_, status=JobStatus.CANCELLING)
        try:
            os.kill(row["pid"], signal.SIGTERM)
        except ProcessLookupError:
            pass
        if table != "runs":
            # A job without checkpoints stops where Python next runs: after the C++ call it is in
            # (SfM can take minutes). Past the grace period it is killed outright.
            threading.Timer(self.kill_after, self._kill_if_alive, args=(row["pid"], id_)).start()
        return True

    kill_after = 15.0  # seconds a cancelled ingest, synthesis or export has to unwind

    @staticmethod
    def _kill_if_alive(pid: int, job_id: str) -> None:
        if job_process(pid, job_id):
            try:
                os.killpg(pid, signal.SIGKILL)  # the job's process group: SfM helpers with it
            except (ProcessLookupError, PermissionError):
                pass

    def recover(self) -> None:
        """After a server restart: jobs whose process survived keep running (watched by polling);
        the others are marked interrupted."""
        for table in ("scenes", "runs", "exports"):
            for row in self.ws.list(table):
                if row["status"] in ACTIVE:
                    if job_process(row["pid"], row["id"]):
                        threading.Thread(target=self._poll_foreign, args=(table, row["id"], row["pid"]), daemon=True).start()
                    else:
                        kept = table == "runs" and last_checkpoint(Path(row["path"])) is not None
                        self.ws.update(
                            table,
                            row["id"],
                            status=JobStatus.INTERRUPTED,
                            pid=None,
                            error="the server stopped while this job ran"
                            + ("; its last checkpoint is kept" if kept else "; it left no checkpoint"),
                        )

    def _poll_foreign(self, table: str, id_: str, pid: int) -> None:
        import time

        while job_process(pid, id_):
            time.sleep(1.0)
        shutil.rmtree(self.tmp_dir(id_), ignore_errors=True)
        row = self.ws.get(table, id_)
        if row and table == "runs":
            info_path = Path(row["path"]) / "run.json"
            status = json.loads(info_path.read_text()).get("status") if info_path.is_file() else "failed"
            self.ws.update(table, id_, status={"training": "interrupted"}.get(status, status), pid=None)
        elif row:
            self.ws.update(table, id_, status=JobStatus.INTERRUPTED, pid=None)

    def shutdown(self) -> None:
        """Leave training jobs running (they survive a server restart); nothing to do."""
