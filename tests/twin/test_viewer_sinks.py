"""A viewer that cannot start never costs the run; --serve binds loopback and serves until Ctrl-C."""

import contextlib
import os
import re
import signal
import socket
import subprocess
import sys
import urllib.request
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]


def twin(*args, env=None):
    return subprocess.run([*TWIN, *args], capture_output=True, text=True, cwd=ROOT, timeout=120, env=env)


@pytest.mark.process
def test_viewer_without_a_display_is_reported_and_the_campaign_runs(tmp_path):
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    res = twin("run", "scenarios/quantum_dots.yaml", "--budget", "3", "--viewer", "--quiet",
               "--journal", str(tmp_path / "j.db"), env=env)
    assert res.returncode == 0, res.stderr
    assert "no display" in res.stderr and "--save" in res.stderr
    assert "3 done" in res.stdout


@pytest.mark.process
def test_serve_on_a_port_in_use_is_reported_and_the_campaign_runs(tmp_path):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        res = twin("run", "scenarios/quantum_dots.yaml", "--budget", "3", "--serve", "--serve-port", str(port),
                   "--save", str(tmp_path / "r.rrd"), "--quiet", "--journal", str(tmp_path / "j.db"))
    assert res.returncode == 0, res.stderr
    assert f"port {port} on 127.0.0.1 is in use" in res.stderr
    assert "3 done" in res.stdout and (tmp_path / "r.rrd").stat().st_size > 0


@pytest.mark.process
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGTERM])
def test_serve_binds_loopback_and_keeps_serving_until_ctrl_c_or_sigterm(tmp_path, stop):
    proc = subprocess.Popen([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "3", "--serve", "--quiet",
                             "--journal", str(tmp_path / "j.db")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        url, line = None, "-"
        while url is None and line:  # readline returns "" once the command has exited
            line = proc.stderr.readline()
            m = re.search(r"the finished campaign is served at (http://\S+)", line)
            url = m.group(1) if m else None
        assert url and url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(url, timeout=10) as page:
            assert page.status == 200
        web_port = int(url.split(":")[2].split("/")[0])
        with socket.socket() as s:  # not reachable on other addresses of this host
            hosts = {a[4][0] for a in socket.getaddrinfo(socket.gethostname(), None, socket.AF_INET)} - {"127.0.0.1"}
            for host in hosts:
                assert s.connect_ex((host, web_port)) != 0
        proc.send_signal(stop)
        proc.wait(timeout=30)
        assert proc.returncode == 0
        with socket.socket() as s:
            assert s.connect_ex(("127.0.0.1", web_port)) != 0, "the server must stop with the command"
    finally:
        proc.kill()


@pytest.mark.process
def test_ctrl_c_stops_the_served_campaign_when_another_thread_receives_it():
    """The kernel may hand a process's SIGINT to any of its threads (Zenoh's, Rerun's): Python then only sets a
    flag, and a main thread blocked in waitpid never looked at it, so `twin run --serve` kept serving."""
    import sys as _sys
    import threading

    import rerun as rr

    from twin.cli.common import keep_serving
    from twin.view import viewer_process
    from twin.view.recorder import Recording, RerunCanvas

    messages: list[str] = []
    served = viewer_process.serve(0, 0, messages)
    assert served is not None, messages
    server, url, _ = served
    rec = rr.RecordingStream("labtwin-test")
    recording = Recording(rec, RerunCanvas(rec), server=server, url=url)
    main, still_serving = threading.main_thread().ident, []

    def interrupt_from_another_thread():
        while True:  # until the main thread waits on the server, past saying where it is served
            frame, names = _sys._current_frames().get(main), []
            while frame is not None:
                names.append(frame.f_code.co_name)
                frame = frame.f_back
            if "keep_serving" in names and "print" not in names:
                break
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)
        try:
            server.wait(timeout=20)
        except subprocess.TimeoutExpired:  # still serving: stop it, so that the test fails instead of hanging
            still_serving.append(True)
            viewer_process.stop(server)

    helper = threading.Thread(target=interrupt_from_another_thread)
    helper.start()
    try:
        keep_serving(recording, stopped="")
    finally:
        helper.join()
    assert not still_serving, "the interrupt must stop the server, not the test's timeout"
    assert recording.server is None and server.poll() is not None


@pytest.mark.process
def test_the_server_ends_with_a_lab_killed_with_sigkill(tmp_path):
    """The `rerun` command is a Python wrapper whose child, the binary, serves: a `twin run --serve` killed with
    SIGKILL (an OOM kill, a CI's timeout) left it serving, its ports held, for good."""
    import time

    proc = subprocess.Popen([*TWIN, "run", "scenarios/quantum_dots.yaml", "--budget", "3", "--serve", "--quiet",
                             "--journal", str(tmp_path / "j.db")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    children: list[int] = []
    try:
        url, line = None, "-"
        while url is None and line:
            line = proc.stderr.readline()
            m = re.search(r"the finished campaign is served at (http://\S+)", line)
            url = m.group(1) if m else None
        assert url, proc.stderr.read()
        for task in Path(f"/proc/{proc.pid}/task").iterdir():
            children += [int(p) for p in (task / "children").read_text().split()]
        assert children
        web_port = int(url.split(":")[2].split("/")[0])
        proc.kill()
        proc.wait(timeout=30)
        deadline = time.monotonic() + 20  # wall time: the OS delivering a signal to another process
        while any(Path(f"/proc/{pid}").exists() and "zombie" not in _state(pid) for pid in children):
            assert time.monotonic() < deadline, f"the server outlived the lab: {children}"
            time.sleep(0.1)

        def listening() -> bool:
            with socket.socket() as s:
                return s.connect_ex(("127.0.0.1", web_port)) == 0

        while listening():  # a leader thread shows as a zombie while the server's other threads still close up
            assert time.monotonic() < deadline, f"the server's port {web_port} outlived the lab"
            time.sleep(0.1)
    finally:
        proc.kill()
        for pid in children:  # what a failure would leave
            with contextlib.suppress(ProcessLookupError):
                os.killpg(pid, signal.SIGKILL)


def _state(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/status").read_text().split("State:")[1].splitlines()[0]
    except (OSError, IndexError):
        return "zombie"
