"""Render a real screenshot of the Rerun web viewer showing a finished campaign: docs/viewer.png.

    apt-get install -y chromium                  # Debian's browser
    .venv/bin/pip install playwright             # drives it (no browser download: uses /usr/bin/chromium)
    .venv/bin/python scripts/viewer_screenshot.py [scenario] [--budget N] [--out docs/viewer.png]

It runs the campaign with --save, serves the recording with `rerun --serve-web`
bound to 127.0.0.1, opens the web viewer in headless Chromium (software WebGL),
waits for it to draw, and saves the page.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(port: int, seconds: float = 20) -> None:
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.1)
    raise SystemExit(f"the rerun web viewer did not come up on port {port}")


async def screenshot(url: str, out: Path, wait_s: float) -> None:
    from playwright.async_api import async_playwright

    async with async_playwright() as p:
        browser = await p.chromium.launch(executable_path=CHROMIUM, headless=True, args=[
            "--no-sandbox", "--disable-quic", "--no-first-run", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
        page = await browser.new_page(viewport={"width": 1600, "height": 1000})
        await page.goto(url)
        await page.wait_for_timeout(wait_s * 1000)
        await page.screenshot(path=str(out))
        await browser.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenario", nargs="?", default="scenarios/flaky_lab.yaml")
    ap.add_argument("--budget", type=int, default=30)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "viewer.png")
    ap.add_argument("--wait", type=float, default=25.0, help="seconds to let the viewer draw")
    args = ap.parse_args()
    if not Path(CHROMIUM).exists():
        raise SystemExit("no Chromium at /usr/bin/chromium: apt-get install -y chromium")
    try:
        import playwright  # noqa: F401
    except ImportError:
        raise SystemExit("playwright is missing: .venv/bin/pip install playwright") from None
    bin_dir = Path(sys.executable).parent
    rerun = str(bin_dir / "rerun") if (bin_dir / "rerun").exists() else shutil.which("rerun")
    with tempfile.TemporaryDirectory() as d:
        rrd = Path(d) / "run.rrd"
        subprocess.run([str(bin_dir / "twin"), "run", args.scenario, "--budget", str(args.budget), "--seed",
                        str(args.seed), "--bus", "memory", "--save", str(rrd), "--journal", str(Path(d) / "j.db"),
                        "--quiet"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
        grpc, web = free_port(), free_port()
        server = subprocess.Popen([rerun, "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
                                   "--web-viewer-port", str(web), str(rrd)],
                                  stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            wait_listening(web)
            url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy"
            asyncio.run(screenshot(url, args.out, args.wait))
        finally:  # the rerun command is a wrapper: end its whole process group
            os.killpg(server.pid, signal.SIGTERM)
            server.wait()
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
