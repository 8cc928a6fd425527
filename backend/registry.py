"""The workspace: a folder plus a SQLite registry of scenes, runs and exports.

```
WORKSPACE/
  workspace.db        the registry (this module)
  scenes/<id>/        scene folders (synthesized, ingested, uploaded)
  runs/<id>/          run directories (kgs_core.run), one per training job
  exports/<id>/       export outputs
  jobs/<id>.log       stdout/stderr of each job process
```

Resources are addressed by registry ids (12 hex digits), never by paths: a client cannot make
the server read or write outside the workspace. Paths passed to `kgs-app serve PATH...` are
registered at start-up (scene folders and run directories).

Paths inside the workspace are stored relative to it (absolute ones only for folders
registered from elsewhere), and rows come back with absolute paths: a copied or moved
workspace finds its own folders, instead of listing every run twice and writing edits into
the original.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import threading
import time
import uuid
from contextlib import contextmanager
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Iterator

SCHEMA = """
CREATE TABLE IF NOT EXISTS scenes (
  id TEXT PRIMARY KEY, name TEXT NOT NULL, path TEXT NOT NULL UNIQUE, source TEXT NOT NULL,
  status TEXT NOT NULL, error TEXT, created REAL NOT NULL, pid INTEGER);
CREATE TABLE IF NOT EXISTS runs (
  id TEXT PRIMARY KEY, scene_id TEXT, name TEXT NOT NULL, path TEXT NOT NULL UNIQUE, status TEXT NOT NULL,
  error TEXT, params TEXT NOT NULL DEFAULT '{}', created REAL NOT NULL, pid INTEGER);
CREATE TABLE IF NOT EXISTS exports (
  id TEXT PRIMARY KEY, run_id TEXT NOT NULL, format TEXT NOT NULL, path TEXT NOT NULL, status TEXT NOT NULL,
  error TEXT, params TEXT NOT NULL DEFAULT '{}', created REAL NOT NULL, pid INTEGER);
"""

TABLES = ("scenes", "runs", "exports")


class JobStatus(str, Enum):
    """The `status` of a scene, run or export in the registry. A `str` enum: rows read back from
    SQLite are plain strings and compare equal to its members."""

    UPLOADED = "uploaded"  # scenes: a video kept for an ingest not started yet
    QUEUED = "queued"
    RUNNING = "running"
    CANCELLING = "cancelling"  # asked to stop; its process has not exited yet
    CANCELLED = "cancelled"
    DONE = "done"
    FAILED = "failed"
    INTERRUPTED = "interrupted"  # the server stopped while it ran (a run resumes from its checkpoint)

    def __str__(self) -> str:
        return self.value


# A process is, or is about to be, working on the row: it cannot be deleted or started again.
ACTIVE = frozenset({JobStatus.QUEUED, JobStatus.RUNNING, JobStatus.CANCELLING})
# What a cancel can still stop.
CANCELLABLE = frozenset({JobStatus.QUEUED, JobStatus.RUNNING})


def relative_text(text: str, *roots: Path) -> str:
    """`text` with each of `roots` (and its resolved form) removed from the paths it names:
    answers name files relative to the workspace (or a dataset), never the server's folders."""
    for root in roots:
        for form in sorted({str(Path(root).resolve()), str(root)}, key=len, reverse=True):
            text = text.replace(form + "/", "").replace(form, ".")
    return text


def new_id() -> str:
    return uuid.uuid4().hex[:12]


@dataclass
class Workspace:
    root: Path

    # The job runner's queue (`JobRunner.position`): a queued row's place in it.
    queue_position: object = None

    def __post_init__(self) -> None:
        self.root = Path(self.root).resolve()
        for sub in ("scenes", "runs", "exports", "jobs"):
            (self.root / sub).mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        with self._connect() as db:
            db.executescript(SCHEMA)
            # Registries written before paths were stored relative: rewrite those inside.
            for table in TABLES:
                for id_, path in db.execute(f"SELECT id, path FROM {table}").fetchall():
                    if Path(path).is_absolute() and (kept := self._stored(path)) != path:
                        db.execute(f"UPDATE {table} SET path = ? WHERE id = ?", (kept, id_))

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        """A connection for one transaction, committed (or rolled back) and closed: a
        connection's own `with` only commits, and the handles of every request piled up."""
        db = sqlite3.connect(self.root / "workspace.db", timeout=30)
        db.row_factory = sqlite3.Row
        try:
            with db:
                yield db
        finally:
            db.close()

    # ------------------------------------------------------------ generic rows

    def insert(self, table: str, **row) -> dict:
        assert table in TABLES
        row.setdefault("id", new_id())
        row.setdefault("created", time.time())
        if "params" in row and not isinstance(row["params"], str):
            row["params"] = json.dumps(row["params"])
        if "path" in row:
            row["path"] = self._stored(row["path"])
        cols = ", ".join(row)
        with self._lock, self._connect() as db:
            db.execute(f"INSERT INTO {table} ({cols}) VALUES ({', '.join('?' * len(row))})", tuple(row.values()))
        return self.get(table, row["id"])

    def get(self, table: str, id_: str) -> dict | None:
        assert table in TABLES
        with self._connect() as db:
            r = db.execute(f"SELECT * FROM {table} WHERE id = ?", (id_,)).fetchone()
        return self._row(r)

    def find_path(self, table: str, path: Path) -> dict | None:
        with self._connect() as db:
            r = db.execute(f"SELECT * FROM {table} WHERE path = ?", (self._stored(path),)).fetchone()
        return self._row(r)

    def list(self, table: str, **where) -> list[dict]:
        assert table in TABLES
        q, args = f"SELECT * FROM {table}", ()
        if where:
            q += " WHERE " + " AND ".join(f"{k} = ?" for k in where)
            args = tuple(where.values())
        with self._connect() as db:
            return [self._row(r) for r in db.execute(q + " ORDER BY created", args).fetchall()]

    def update(self, table: str, id_: str, **fields) -> None:
        assert table in TABLES
        if "params" in fields and not isinstance(fields["params"], str):
            fields["params"] = json.dumps(fields["params"])
        if "path" in fields:
            fields["path"] = self._stored(fields["path"])
        with self._lock, self._connect() as db:
            db.execute(f"UPDATE {table} SET {', '.join(f'{k} = ?' for k in fields)} WHERE id = ?", (*fields.values(), id_))

    def delete(self, table: str, id_: str) -> None:
        self.remove([(table, id_)])

    def transition(self, table: str, id_: str, allowed, **fields) -> bool:
        """Sets `fields` only if the row's status is one of `allowed`, in one statement: of two
        requests racing to start a job on a row, one wins and the other learns it lost."""
        assert table in TABLES
        allowed = [str(a) for a in allowed]
        with self._lock, self._connect() as db:
            cur = db.execute(
                f"UPDATE {table} SET {', '.join(f'{k} = ?' for k in fields)} WHERE id = ? AND status IN ({', '.join('?' * len(allowed))})",
                (*map(str, fields.values()), id_, *allowed),
            )
            return cur.rowcount == 1

    def remove(self, rows: list[tuple[str, str]], files: list[Path] = ()) -> None:
        """Deletes `rows` ((table, id) pairs) and `files` (folders or files inside the
        workspace) together: the files are first renamed aside, the rows deleted in one
        transaction, and only then the files removed; if the registry cannot be written (a full
        disk) the files are renamed back and the error raised, so nothing is half-deleted."""
        aside = []
        for path in files:
            path = Path(path)
            if path.exists() and path.resolve().is_relative_to(self.root):
                moved = path.with_name(f".deleting-{new_id()}-{path.name}")
                path.rename(moved)
                aside.append((path, moved))
        try:
            with self._lock, self._connect() as db:
                for table, id_ in rows:
                    assert table in TABLES
                    db.execute(f"DELETE FROM {table} WHERE id = ?", (id_,))
        except BaseException:
            for path, moved in reversed(aside):
                moved.rename(path)
            raise
        for _, moved in aside:
            if moved.is_dir():
                shutil.rmtree(moved, ignore_errors=True)
            else:
                moved.unlink(missing_ok=True)

    def new_dir(self, kind: str, id_: str) -> Path:
        return self.root / kind / id_

    # ------------------------------------------------------------ paths

    def _stored(self, path: str | Path) -> str:
        """How a path is kept: relative (POSIX) when inside the workspace, else absolute."""
        p = Path(path).resolve()
        return p.relative_to(self.root).as_posix() if p.is_relative_to(self.root) else str(p)

    def _row(self, r) -> dict | None:
        if r is None:
            return None
        d = dict(r)
        if "params" in d:
            d["params"] = json.loads(d["params"] or "{}")
        if "path" in d:
            d["path"] = str(self.root / d["path"])  # an absolute stored path stays as it is
        if "status" in d:
            d["queue_position"] = self.queue_position(d["id"]) if self.queue_position and d["status"] == "queued" else None
        return d
