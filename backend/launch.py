"""Starting `kgs-app serve` as a child process on a free loopback port and waiting until it
answers (benchmarks and tests talk to a real server this way)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """`with ServerProcess([run_dir], workspace) as srv:` → `srv.base` (URL), `srv.runs` (the
    registered runs as listed by the API). Stopped (SIGTERM) on exit."""

    def __init__(self, paths: list[Path], workspace: Path, timeout: float = 60.0, token: str | None = None):
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "kgs_app.cli",
                "serve",
                *map(str, paths),
                "--workspace",
                str(workspace),
                "--port",
                str(self.port),
                *(["--token", token] if token else []),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        runs = urllib.request.Request(self.base + "/api/runs", headers={"X-KGS-Token": token} if token else {})
        deadline = time.time() + timeout
        while True:
            try:
                self.runs = json.loads(urllib.request.urlopen(runs).read())
                break
            except OSError:
                if self.proc.poll() is not None or time.time() > deadline:
                    self.stop()
                    raise RuntimeError(f"kgs-app serve did not start: {self.proc.stdout.read()[-2000:]}")
                time.sleep(0.1)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(10)

    def __enter__(self) -> "ServerProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
