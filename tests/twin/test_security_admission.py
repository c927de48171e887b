"""Whom a secure router admits: the devices its security directory named when it started, and what is said of the
others — by the router when `twin security init` adds one while it runs, and by a lab told to wait for one."""

import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.shared_labs import lines_until
from tests.twin.test_device_process import free_port
from tests.twin.test_security import session
from twin.core import keys
from twin.core.bus.router import AdmittedDevices
from twin.core.bus.security import Identity, session_config
from twin.core.errors import TwinError
from twin.runtime.lab import prepare, refuse_external
from twin.tools.security_init import init

ROOT = Path(__file__).resolve().parents[2]
LAB = "t"


def test_a_device_added_to_the_directory_is_named_once_as_not_admitted(tmp_path):
    init(tmp_path, LAB, ["synthesiser"])
    admitted = AdmittedDevices(str(tmp_path))
    assert "devices: synthesiser (" in admitted.said() and admitted.news() == []
    init(tmp_path, LAB, ["spectrometer-1", "spectrometer-2"])
    (warning,) = admitted.news()
    assert "names devices spectrometer-1, spectrometer-2 of lab t, which this router does not admit" in warning
    assert "Restart this `twin router`" in warning
    init(tmp_path, LAB, ["spectrometer-1"])  # rewritten, nothing new
    assert admitted.news() == [] and admitted.devices == {"synthesiser"}


def test_a_lab_refuses_to_wait_for_an_external_device_its_router_would_not_admit(tmp_path):
    init(tmp_path / "sec", LAB, ["synthesiser"])
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump({**qd_lab(**{
        "clock": {"mode": "scaled", "speed": 100.0},
        "bus": {"kind": "zenoh", "listen": [], "connect": ["tls/127.0.0.1:7447"], "security": "sec"}}), "lab": LAB}))
    s = prepare(path)
    refuse_external(s, {"synthesiser"})
    with pytest.raises(TwinError, match=r"--external spectrometer-1, spectrometer-2: .*sec has no certificate for "
                                        r"them.*--device spectrometer-1 --device spectrometer-2`.*restart `twin "
                                        r"router`"):
        refuse_external(s, {"synthesiser", "spectrometer-1", "spectrometer-2"})


@pytest.mark.process
def test_a_running_router_names_a_device_added_since_it_started_and_admits_it_only_once_restarted(tmp_path):
    init(tmp_path, LAB, ["synthesiser"])
    endpoint = f"tls/127.0.0.1:{free_port()}"

    def router() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "twin", "router", "--listen", endpoint, "--security",
                                 str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)

    first = router()
    try:
        lines_until(first.stderr, {"lab t: admitting its orchestrator, scheduler agent, watchers, operators and "
                                   "devices: synthesiser ("})
        init(tmp_path, LAB, ["spectrometer"])
        lines_until(first.stderr, {"names device spectrometer of lab t, which this router does not admit"})
        assert _heard(endpoint, tmp_path) is False  # connected, and refused: as the warning says
    finally:
        first.terminate()
        first.wait(10)
    again = router()
    try:
        lines_until(again.stderr, {"devices: spectrometer, synthesiser ("})
        assert _heard(endpoint, tmp_path) is True
    finally:
        again.terminate()
        again.wait(10)


def _heard(endpoint: str, root: Path) -> bool:
    """Whether the lab's orchestrator hears an event the spectrometer puts on its own key through the router."""
    heard: list[bytes] = []
    lab = session(endpoint, session_config(root, Identity("orchestrator", LAB)))
    device = session(endpoint, session_config(root, Identity("device", LAB, "spectrometer")))
    try:
        sub = lab.declare_subscriber(keys.evt(LAB, "spectrometer"),
                                     lambda sample: heard.append(sample.payload.to_bytes()))
        deadline = time.monotonic() + 3.0
        while not heard and time.monotonic() < deadline:
            device.put(keys.evt(LAB, "spectrometer"), b"{}")
            time.sleep(0.1)  # wall time: what crosses a real router
        sub.undeclare()
    finally:
        device.close()
        lab.close()
    return bool(heard)
