"""Viewer open benchmark: `kgs-app bench open RUN [--repeats N]`.

How long a user waits to see a run in the browser viewer. Each repeat starts a fresh
`kgs-app serve` process on RUN (a cold server: nothing loaded, no caches), opens the run in
headless Chromium (Debian's /usr/bin/chromium, SwiftShader WebGL2), and times from navigation to
the first full frame: the loading overlay gone, both sets drawn. Then the page is reloaded on the
same, now warm, server and timed again. Prints the times and where the cold open spent them
(the overlay's steps as they appeared).
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

from .machine import machine

CHROMIUM = "/usr/bin/chromium"
# The overlay's steps, with the milliseconds since navigation at which each appeared.
WATCH_STEPS = """
  window.openSteps = [];
  document.addEventListener("DOMContentLoaded", () => {
    const el = document.getElementById("loading");
    new MutationObserver(() => { if (!el.hidden) window.openSteps.push([performance.now(), el.textContent]); })
      .observe(el, { childList: true, characterData: true, subtree: true, attributes: true });
  });
"""


def time_open(page, navigate, timeout_ms: int = 120_000) -> tuple[float, list]:
    """Seconds from `navigate()` to the first full frame, and the overlay's steps on the way."""
    t0 = time.perf_counter()
    navigate()
    page.wait_for_selector("body[data-ready='1']", timeout=timeout_ms)
    page.wait_for_function("document.getElementById('loading').hidden", timeout=timeout_ms)
    page.evaluate("kgs.drawn()")
    seconds = time.perf_counter() - t0
    steps = page.evaluate("window.openSteps")
    return seconds, [(round(ms / 1000, 2), text) for ms, text in steps]


def launch_chromium(pw):
    return pw.chromium.launch(
        executable_path=CHROMIUM, args=["--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
    )


def measure(run: Path, repeats: int, browser, log=print) -> tuple[list[float], list[float]]:
    """(cold seconds, reload seconds) per repeat, each on a fresh server for `run`."""
    from kgs_backend.launch import ServerProcess

    cold, warm = [], []
    for r in range(repeats):
        root = Path(tempfile.mkdtemp(prefix="kgs-bench-open-"))
        try:
            with ServerProcess([run.resolve()], root / "ws") as srv:
                ctx = browser.new_context(viewport={"width": 1100, "height": 700})
                page = ctx.new_page()
                page.add_init_script(WATCH_STEPS)
                url = f"{srv.base}/#/run/{srv.runs[0]['id']}"
                s_cold, steps = time_open(page, lambda: page.goto(url))
                s_warm, _ = time_open(page, page.reload)
                cold.append(s_cold)
                warm.append(s_warm)
                log(f"repeat {r + 1}: cold {s_cold:.2f} s, reload {s_warm:.2f} s; cold steps: " + json.dumps(steps, ensure_ascii=False))
                ctx.close()
        finally:
            shutil.rmtree(root, ignore_errors=True)
    return cold, warm


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="kgs-app bench open", description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path, help="a run directory (e.g. workspace/runs/sheet-fast from `kgs-app demo`)")
    p.add_argument("--repeats", type=int, default=3, help="cold servers to start, one open and one reload each")
    args = p.parse_args(argv)
    if not (args.run / "model.pt").is_file():
        p.error(f"{args.run} is not a finished run (no model.pt)")
    if not Path(CHROMIUM).exists():
        p.error(f"{CHROMIUM} is missing (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    print(f"machine: {machine()}")
    with sync_playwright() as pw:
        browser = launch_chromium(pw)
        cold, warm = measure(args.run, args.repeats, browser)
        browser.close()
    print(f"first full frame, cold server: median {statistics.median(cold):.2f} s (min {min(cold):.2f}, max {max(cold):.2f})")
    print(f"first full frame, reload:      median {statistics.median(warm):.2f} s (min {min(warm):.2f}, max {max(warm):.2f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
