"""Server settings (from `kgs-app serve` options)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass
class Settings:
    workspace: Path
    host: str = "127.0.0.1"
    port: int = 8000
    token: str | None = None  # required on every API call and WebSocket when set
    cors_origins: list[str] = field(default_factory=list)  # CORS stays off unless origins are given
    allowed_hosts: list[str] = field(default_factory=list)  # Host names answered besides the bound one and loopback
    max_upload_mb: int = 512
    register: list[Path] = field(default_factory=list)  # scene folders / run directories to add at start-up
    start_demo: object = None  # callable(app) run once at start-up (`--demo` on an empty workspace)

    @property
    def loopback(self) -> bool:
        return self.host in LOOPBACK
