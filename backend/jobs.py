"""Starting, watching and cancelling job processes (`kgs_backend.worker`).

A job is a registry row (a scene, run or export) with `status` queued → running → done | failed
| cancelled, the `pid` of its process and, on failure, the error. A watcher thread per job
waits for the process and records how it ended; at start-up `recover` marks jobs whose process
is gone as `interrupted` (a training run keeps its checkpoints and can be resumed).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

from kgs_core.threads import cores_to_use, placement_env, placement_off

from .registry import ACTIVE, CANCELLABLE, JobStatus, Workspace


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


class JobRunner:
    def __init__(self, ws: Workspace):
        self.ws = ws
        self.procs: dict[str, subprocess.Popen] = {}

    def start(self, table: str, id_: str, kind: str, spec: dict, on_done=None) -> None:
        log = open(self.ws.root / "jobs" / f"{id_}.log", "ab")
        cores = self.share(len(self.live()) + 1)
        # The count is the runner's choice, not the user's: the job's ThreadTuner may change it
        # (unless the server itself was given a fixed count, which its KGS_OMP_FROM_USER says).
        placement = {**placement_env(cores), "KGS_OMP_FROM_USER": os.environ.get("KGS_OMP_FROM_USER", "0")} if cores else {}
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **placement}
        proc = subprocess.Popen([sys.executable, "-m", "kgs_backend.worker", kind, json.dumps(spec)],
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
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
        self.procs.pop(id_, None)
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
        root = str(self.ws.root.resolve()) + os.sep
        lines = [ln.replace(root, "") for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
        for ln in reversed(lines):
            if ln and not ln.startswith(" ") and ("Error" in ln or "Exception" in ln):
                return ln[-2000:]
        return lines[-1][-2000:] if lines else None

    def cancel(self, table: str, id_: str) -> bool:
        row = self.ws.get(table, id_)
        if row is None or row["status"] not in CANCELLABLE or not pid_alive(row["pid"]):
            return False
        self.ws.update(table, id_, status=JobStatus.CANCELLING)
        try:
            os.kill(row["pid"], signal.SIGTERM)
        except ProcessLookupError:
            pass
        if table != "runs":
            # A job without checkpoints stops where Python next runs: after the C++ call it is in
            # (SfM can take minutes). Past the grace period it is killed outright.
            threading.Timer(self.kill_after, self._kill_if_alive, args=(row["pid"],)).start()
        return True

    kill_after = 15.0  # seconds a cancelled ingest, synthesis or export has to unwind

    @staticmethod
    def _kill_if_alive(pid: int) -> None:
        if pid_alive(pid):
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
                    if pid_alive(row["pid"]):
                        threading.Thread(target=self._poll_foreign, args=(table, row["id"], row["pid"]),
                                         daemon=True).start()
                    else:
                        kept = table == "runs" and last_checkpoint(Path(row["path"])) is not None
                        self.ws.update(table, row["id"], status=JobStatus.INTERRUPTED, pid=None,
                                       error="the server stopped while this job ran"
                                       + ("; its last checkpoint is kept" if kept else "; it left no checkpoint"))

    def _poll_foreign(self, table: str, id_: str, pid: int) -> None:
        import time

        while pid_alive(pid):
            time.sleep(1.0)
        row = self.ws.get(table, id_)
        if row and table == "runs":
            info_path = Path(row["path"]) / "run.json"
            status = json.loads(info_path.read_text()).get("status") if info_path.is_file() else "failed"
            self.ws.update(table, id_, status={"training": "interrupted"}.get(status, status), pid=None)
        elif row:
            self.ws.update(table, id_, status=JobStatus.INTERRUPTED, pid=None)

    def shutdown(self) -> None:
        """Leave training jobs running (they survive a server restart); nothing to do."""
