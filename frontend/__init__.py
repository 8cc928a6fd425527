"""The browser client, shipped as package data (`kgs_frontend`): plain ES modules, CSS and the
GLSL shaders that the browser and the desktop viewer share. The server serves `ROOT` as it is
(no build step)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parent
