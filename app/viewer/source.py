"""Where the viewer's splats come from: a run directory loaded in process (no server), or a
running `kgs-app serve` (REST + the WebSocket splat stream). Both hand out `SplatSet`s parsed
from the same KGS1 buffers the browser gets."""

from __future__ import annotations

import json
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kgs_core.splat_buffer import unpack_buffer


@dataclass
class SplatSet:
    positions: np.ndarray  # (N, 3) float32
    covars: np.ndarray  # (N, 6) float32: xx, xy, xz, yy, yz, zz
    rgba: np.ndarray  # (N, 4) uint8
    index: np.ndarray  # (N,) uint32
    velocity: np.ndarray | None  # (N, 3) float32
    header: dict

    def __len__(self) -> int:
        return len(self.positions)

    @classmethod
    def parse(cls, data: bytes) -> "SplatSet":
        header, rec, vel = unpack_buffer(data)
        cov = rec["covariance"].astype(np.float32) * np.float32(header["cov_scale"])
        return cls(
            rec["position"].copy(), cov, rec["rgba"].copy(), rec["index"].copy(), None if vel is None else vel.astype(np.float32), header
        )


class LocalSource:
    """A run directory, evaluated in this process (the server's RunView, without the server)."""

    def __init__(self, run_dir: str | Path):
        from kgs_core.run import learned_blur
        from kgs_core.run_view import RunView

        self.view = RunView(Path(run_dir))
        self.frames = self.view.frames()
        run = self.view.run
        self.meta = {
            "name": run.path.name,
            "dt": self.view.dt,
            "exposure": float(run.info.get("exposure", 0.0)),
            "lod_levels": run.n_levels,
            "tau": self.view.tau,
            "histogram": self.view.histogram(),
            "decomposition": self.view.decomposition(),
            "sh_degree": run.model.config.sh_degree,
            "camera_motion": learned_blur(run.info).get("camera_motion"),
        }

    def static(self, lod: int | None) -> SplatSet:
        return SplatSet.parse(self.view.static_buffer(lod))

    def dynamic(self, t: float, exposure: float, lod: int | None) -> SplatSet:
        return SplatSet.parse(self.view.dynamic_buffer(t, exposure, lod))

    def set_tau(self, tau: float) -> dict:
        decomposition = self.view.set_tau(tau)
        self.meta.update(tau=tau, decomposition=decomposition)
        return decomposition


class RemoteSource:
    """A run served by `kgs-app serve` at `url` (e.g. http://127.0.0.1:8000)."""

    def __init__(self, url: str, run_id: str, token: str | None = None):
        self.url, self.run_id, self.token = url.rstrip("/"), run_id, token
        try:
            meta = self._get(f"/api/runs/{run_id}")
        except urllib.error.HTTPError as exc:
            raise ValueError(f"{url}: run {run_id!r}: HTTP {exc.code} {exc.reason}") from None
        except OSError as exc:  # refused, unreachable, bad URL
            raise ValueError(f"cannot reach kgs-app serve at {url}: {exc}") from None
        if not meta.get("has_model"):
            raise ValueError(f"run {run_id} on {url} has no model yet (status {meta.get('status')})")
        self.frames = meta["frames"]
        self.meta = {
            "name": meta["name"],
            "dt": meta["dt"],
            "exposure": meta["exposure"],
            "lod_levels": meta["lod_levels"],
            "tau": meta["tau"],
            "histogram": meta["histogram"],
            "decomposition": meta["decomposition"],
            "sh_degree": meta["sh_degree"],
            "camera_motion": (meta.get("blur") or {}).get("camera_motion"),
        }
        from websockets.sync.client import connect

        ws_url = self.url.replace("http", "ws", 1) + f"/api/runs/{run_id}/stream"
        if token:
            ws_url += "?token=" + urllib.parse.quote(token)
        self._conn = connect(ws_url, max_size=None, compression=None)
        self.ws = self._conn.__enter__()
        self._lod = "unset"
        self._static = None

    def close(self) -> None:
        self._conn.__exit__(None, None, None)

    def _get(self, path: str, body: dict | None = None) -> dict:
        req = urllib.request.Request(
            self.url + path,
            data=None if body is None else json.dumps(body).encode(),
            headers={"Content-Type": "application/json", **({"Authorization": f"Bearer {self.token}"} if self.token else {})},
        )
        with urllib.request.urlopen(req) as r:
            return json.loads(r.read())

    def _recv_buffer(self) -> SplatSet:
        while True:
            m = self.ws.recv()
            if isinstance(m, bytes):
                s = SplatSet.parse(m)
                if s.header["kind"] == "static":
                    self._static = s  # pushed after a τ change or an edit
                return s
            msg = json.loads(m)
            if msg.get("type") == "error":
                raise ValueError(f"server: {msg['message']}")

    def static(self, lod: int | None) -> SplatSet:
        self.ws.send(json.dumps({"type": "subscribe", "lod": lod, "velocity": True}))
        self._static = self._recv_buffer()
        return self._static

    def dynamic(self, t: float, exposure: float, lod: int | None) -> SplatSet:
        self.ws.send(json.dumps({"type": "time", "t": t, "exposure": exposure}))
        while True:
            s = self._recv_buffer()
            if s.header["kind"] == "dynamic":
                return s

    def set_tau(self, tau: float) -> dict:
        decomposition = self._get(f"/api/runs/{self.run_id}/tau", {"tau": tau})
        self.meta.update(tau=tau, decomposition=decomposition)
        return decomposition
