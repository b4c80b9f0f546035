"""The README's snippets run as written (issue 50): the demo on the endpoint the client
snippets use, both client snippets against it, the library snippet and the examples block, the
real-data commands; and facts the README states once (the reconnect backoff) agree with the
code."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from keo_service.bench.procs import free_port, process_group
from keo_service.io.config import load_config
from keo_service.live.backoff import Backoff
from tests.conftest import DEMO, REPO, wait_until

README = REPO / "README.md"


def blocks(language: str) -> list[str]:
    """The README's fenced code blocks of one language, in order."""
    return re.findall(rf"```{language}\n(.*?)```", README.read_text(), re.S)


def block_with(language: str, text: str) -> str:
    found = [b for b in blocks(language) if text in b]
    assert len(found) == 1, (language, text, len(found))
    return found[0]


def commands(block: str) -> list[list[str]]:
    """A shell block's commands (comments dropped, `\\` continuations joined)."""
    out = []
    for raw in block.replace("\\\n", " ").splitlines():
        line = raw.split("#", 1)[0].strip()
        if line:
            out.append(shlex.split(line))
    return out


def run(argv: list[str], cwd: Path, timeout: float = 600.0) -> subprocess.CompletedProcess[str]:
    """A README command as a user types it (`keo` and `python` from this interpreter)."""
    if argv[0] == "keo":
        argv = [sys.executable, "-m", "keo_service.cli", *argv[1:]]
    elif argv[0] == "python":
        argv = [sys.executable, *argv[1:]]
    return subprocess.run(
        argv, cwd=cwd, capture_output=True, text=True, timeout=timeout, check=False
    )


def user_folder(tmp_path: Path) -> Path:
    """A folder that looks like the clone to the README's relative paths."""
    for name in ("configs", "data", "examples"):
        (tmp_path / name).symlink_to(REPO / name)
    return tmp_path


# ---- the demo and the client snippets ----------------------------------------------------------


@pytest.mark.e2e
@pytest.mark.slow  # 40 s: a whole demo; the default run stays under 10 min on 2 cores
def test_the_client_snippets_run_against_the_demo_as_the_readme_starts_it(tmp_path):
    """`keo demo --listen ...` as the README writes it, then both client snippets unchanged
    but for the port (a free one, so that tests never meet)."""
    (demo_line,) = commands(block_with("sh", "keo demo --listen"))
    snippets = [block_with("python", "async with Client("), block_with("python", "SyncClient(")]
    endpoint = demo_line[demo_line.index("--listen") + 1]
    cell = load_config(DEMO).cell
    for code in snippets:  # the snippets use what the demo command gives
        assert f'"{endpoint}"' in code
        assert f'cell="{cell}"' in code
    mine = f"tcp/127.0.0.1:{free_port()}"
    argv = [mine if a == endpoint else a for a in demo_line[1:]]
    argv[argv.index("--duration") + 1] = "25"  # the README's 60 s leaves time to type
    snippets = [code.replace(endpoint, mine) for code in snippets]
    with process_group(tmp_path) as procs:
        demo = procs.start("demo", argv)
        wait_until(lambda: f"listens on {mine}" in procs.log("demo"), 60, "the demo's endpoint")
        first = procs.start("snippet-async", ["-c", snippets[0]], module=None)
        wait_until(lambda: first.poll() is not None, 120, "the async snippet ended")
        second = procs.start("snippet-sync", ["-c", snippets[1]], module=None)
        # it ends 10 s after the last estimate, i.e. after the demo
        wait_until(lambda: second.poll() is not None, 90, "the sync snippet ended")
        demo.wait(timeout=60)
    assert demo.returncode == 0, procs.log("demo")
    assert re.search(r"estimates received: [1-9]\d*", procs.log("demo")), procs.log("demo")
    for name, proc in (("snippet-async", first), ("snippet-sync", second)):
        log = procs.log(name)
        assert proc.returncode == 0, log
        assert sum(" ok [" in line for line in log.splitlines()) >= 1, log
    assert "latest: EstimateMessage(" in procs.log("snippet-async")
    assert sum(" ok [" in line for line in procs.log("snippet-sync").splitlines()) > 50


@pytest.mark.e2e
@pytest.mark.slow  # a whole keo demo (40 s in CI): the default run stays under 10 minutes
def test_the_demo_says_why_steps_were_held_and_leaves_no_temp_folder(tmp_path):
    import json
    import os

    from keo_service.bench.demo import HELD_WHY

    env = {**os.environ, "TMPDIR": str(tmp_path)}  # where tempfile puts the demo's folder
    argv = [sys.executable, "-m", "keo_service.cli", "demo", "--duration", "15", "--json"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=180, env=env, check=False)
    assert done.returncode == 0, done.stderr
    summary = json.loads(done.stdout)
    assert re.search(r"the service listens on tcp/127\.0\.0\.1:\d+ ", done.stderr)
    assert summary["endpoint"] in done.stderr
    assert summary["held"] == sum(summary["held_reasons"].values())
    assert set(summary["held_reasons"]) <= set(HELD_WHY)
    assert summary["logs"] is None  # a good run: removed
    assert not list(tmp_path.glob("keo-demo-*"))
    # --logs keeps them where asked
    logs = tmp_path / "logs"
    argv = [*argv[:-1], "--logs", str(logs), "--json"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=180, env=env, check=False)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout)["logs"] == str(logs)
    assert (logs / "service.log").is_file()


def test_the_demo_refuses_a_busy_listen_endpoint_and_says_why():
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        done = run(["keo", "demo", "--listen", f"tcp/127.0.0.1:{port}"], REPO, timeout=60)
    assert done.returncode == 2
    assert f"cannot listen on tcp/127.0.0.1:{port}" in done.stderr
    done = run(["keo", "demo", "--listen", "127.0.0.1:7447"], REPO, timeout=60)
    assert done.returncode == 2
    assert "is not tcp/HOST:PORT" in done.stderr


# ---- the library snippet and the examples block ----------------------------------------------


def test_the_examples_block_and_the_library_snippet_run_as_written(tmp_path):
    folder = user_folder(tmp_path)
    block = blocks("bash")[-1]
    assert "examples/" in block
    for argv in commands(block):
        done = run(argv, folder)
        assert done.returncode == 0, (argv, done.stderr)
    done = run(["python", "-c", block_with("python", "from keo_service import calibrate_delay")],
               folder)  # fmt: skip
    assert done.returncode == 0, done.stderr
    found = re.search(r"delay ([\d.]+) \+/- ([\d.]+) ms", done.stdout)
    assert found, done.stdout
    # the simulator injects 28 ms (docs/design.md §7)
    assert abs(float(found.group(1)) - 28.0) < 2.0
    assert (folder / "est.csv").is_file()


# ---- the real data -------------------------------------------------------------------------


@pytest.mark.slow
def test_the_real_data_commands_run_as_written(tmp_path):
    """Both UR10 series imported and analyzed, then compensate with Series B's model (the
    targets file the README leaves to the user: the first joint rows of Series B)."""
    folder = user_folder(tmp_path)
    block = block_with("sh", "keo import ur10-lasertracker")
    argvs = commands(block)
    assert any("Series_A" in " ".join(a) for a in argvs)
    assert any("Series_B" in " ".join(a) for a in argvs)
    for argv in argvs:
        if "compensate" in argv:
            q = np.loadtxt(folder / "ur10_B" / "encoder.csv", delimiter=",", skiprows=1)[:5, 1:]
            header = ",".join(f"q{i + 1}" for i in range(q.shape[1]))
            np.savetxt(folder / "my_program.csv", q, delimiter=",", header=header, comments="")
        started = time.monotonic()
        done = run(argv, folder, timeout=3600)
        assert done.returncode == 0, (argv, done.stderr[-2000:])
        print(f"{' '.join(argv[:2])}: {time.monotonic() - started:.0f} s")
    for series in ("A", "B"):
        assert (folder / f"ur10_{series}" / "analysis" / "report.md").is_file()
    assert (folder / "compensated.csv").is_file()


# ---- facts stated once -----------------------------------------------------------------------


def test_the_reconnect_backoff_is_stated_once_and_as_the_code_does_it():
    docs = [README, *sorted((REPO / "docs").glob("*.md"))]
    stated = [
        (path.name, line)
        for path in docs
        if path.name != "README.template.md"
        for line in path.read_text().splitlines()
        if "doubling" in line
    ]
    assert len(stated) == 1, stated
    text = " ".join(README.read_text().split())
    found = re.search(
        r"retried after ([\d.]+) s, the wait doubling to at most ([\d.]+) s, each wait drawn "
        r"within ±(\d+) %",
        text,
    )
    assert found, "the README's Reconnects paragraph"
    backoff = Backoff()
    assert float(found.group(1)) == backoff.initial
    assert float(found.group(2)) == backoff.maximum
    assert backoff.factor == 2.0
    waits = [Backoff(maximum=backoff.maximum) for _ in range(200)]
    capped = []
    for b in waits:
        for _ in range(12):
            last = b.next_delay()
        capped.append(last)
    jitter = float(found.group(3)) / 100
    assert min(capped) >= backoff.maximum * (1 - jitter)
    assert max(capped) <= backoff.maximum * (1 + jitter)
    assert "capped at 2 s" in text
    bus = (REPO / "keo_service" / "live" / "bus.py").read_text()
    assert bus.count("Backoff(maximum=2.0)") == 2


def test_the_readme_names_the_published_patent_application():
    text = " ".join(README.read_text().split())
    for number in ("US 2023/0075352 A1", "WO 2021/174022 A1"):
        assert number in text
    assert "not legal advice" in text
