"""Look at the live view as a person would: run `keo demo` with Rerun's web viewer, open the
page in Chromium on a virtual screen and photograph the screen into docs/viewer.png.

    python docs/screenshot_viewer.py [--out docs/viewer.png] [--size 1600x1000] [--after 45]

Needs Xvfb, Chromium and ImageMagick (Debian: apt-get install chromium imagemagick xvfb).
Not part of the test suite. WebGL runs on the CPU (SwiftShader through ANGLE): Chromium's
`--headless --screenshot` captures only the viewer's loading screen, a window on Xvfb
grabbed with ImageMagick's `import` shows the page as drawn.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from keo_service.live.rerun_process import grpc_url, web_url

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


def wait_port(port: int, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.5):
            return
        time.sleep(0.2)
    raise SystemExit(f"nothing listens on port {port} after {timeout:g} s")


def stop(proc: subprocess.Popen[bytes], sig: int = signal.SIGTERM) -> None:
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "viewer.png")
    parser.add_argument("--size", default="1600x1000")
    parser.add_argument(
        "--after",
        type=float,
        default=45.0,
        help="seconds of demo before the shot (past the plots' 30 s, the start-up swing has "
        "scrolled out; on a busy machine the picture also lags behind)",
    )
    parser.add_argument("--robot", default="mh180")
    parser.add_argument("--colors", type=int, default=128, help="palette of the PNG")
    args = parser.parse_args()
    for tool in ("Xvfb", "chromium", "import", "convert"):
        if shutil.which(tool) is None:
            raise SystemExit(f"{tool} is not installed (apt-get install chromium imagemagick xvfb)")
    width, height = (int(v) for v in args.size.split("x"))
    grpc_port, web_port = free_port(), free_port()
    display = f":{90 + os.getpid() % 100}"
    tmp = Path(tempfile.mkdtemp(prefix="keo-shot-"))
    env = dict(os.environ, DISPLAY=display)
    procs: list[subprocess.Popen[bytes]] = []
    demo = None
    try:
        procs.append(
            subprocess.Popen(
                ["Xvfb", display, "-screen", "0", f"{width}x{height}x24", "-nolisten", "tcp"],
                stderr=subprocess.DEVNULL,
            )
        )
        demo_cmd = [sys.executable, "-m", "keo_service.cli", "demo", "--robot", args.robot]
        demo_cmd += ["--duration", repr(args.after + 20.0), "--viewer", "web"]
        demo_cmd += ["--viewer-port", str(grpc_port), "--web-port", str(web_port)]
        demo_env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
        demo = subprocess.Popen(
            demo_cmd, env=demo_env, stdout=(tmp / "demo.out").open("wb"), stderr=subprocess.STDOUT
        )
        procs.append(demo)
        wait_port(web_port, 60.0)
        url = web_url("127.0.0.1", web_port, grpc_url("127.0.0.1", grpc_port))
        started = time.monotonic()
        chrome = [
            "chromium",
            "--no-sandbox",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            "--no-first-run",
            "--disable-features=Translate",
            f"--user-data-dir={tmp / 'profile'}",
            "--use-gl=angle",
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            "--window-position=0,0",
            f"--window-size={width},{height}",
            "--kiosk",
            url,
        ]
        procs.append(
            subprocess.Popen(
                chrome, env=env, stdout=subprocess.DEVNULL, stderr=(tmp / "chromium.log").open("wb")
            )
        )
        time.sleep(max(0.0, args.after - (time.monotonic() - started)))
        raw = tmp / "screen.png"
        subprocess.run(["import", "-display", display, "-window", "root", str(raw)], check=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(
            ["convert", str(raw), "-colors", str(args.colors), f"PNG8:{args.out}"], check=True
        )
        print(f"{args.out}: {args.out.stat().st_size / 1e3:.0f} kB ({url}; logs in {tmp})")
    finally:
        for proc in reversed(procs):  # the demo as by Ctrl-C: it stops its cell and viewer
            stop(proc, signal.SIGINT if proc is demo else signal.SIGTERM)
    return 0


if __name__ == "__main__":
    sys.exit(main())
