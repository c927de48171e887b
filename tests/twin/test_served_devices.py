"""A device served by another process runs by its own copy of the scenario: the lab names what differs from its
own when the device joins (its durations, faults, options, the chemistry it simulates), and nothing when nothing
does."""

import json
import logging
from pathlib import Path

import pytest
import yaml

from tests.conftest import qd_lab
from tests.twin.test_device_process import free_port
from tests.twin.test_distributed_lab import start
from twin import DeviceActor, StepResult
from twin.campaign.events import Note, alert_text
from twin.campaign.journal_read import read_events
from twin.core.bus import open_bus
from twin.runtime.lab import make_clock, prepare, run_async
from twin.runtime.serve import health
from twin.runtime.served_devices import ServedCheck, differences, served_as
from twin.scenario import parse

SPEED = 400.0


class Reader:
    capabilities = frozenset({"measure"})

    async def run(self, step, params, sample, ctx):
        return StepResult({"peak_nm": 600.0}, sample)

    async def safe_state(self):
        pass


def test_differences_name_the_fields_and_a_files_folder_is_not_one():
    lab = parse(qd_lab(**{"devices.spectrometer.options": {"stock": "/lab/host/stock.csv", "lamp": "uv"}}))
    theirs = parse(qd_lab(**{"devices.spectrometer.options": {"stock": "/device/host/stock.csv", "lamp": "vis"},
                             "devices.spectrometer.duration": {"mean_s": 5000, "cv": 0.1},
                             "devices.spectrometer.faults": {"fail_p": 0.2},
                             "devices.spectrometer.cost": 99, "chemistry.noise": 0.5}))
    found = differences(served_as(lab, "spectrometer"), served_as(theirs, "spectrometer"), "spectrometer")
    assert found == ["devices.spectrometer.duration.mean_s: 5000.0 there, 60.0 here",
                     "devices.spectrometer.faults.fail_p: 0.2 there, 0.0 here",
                     'devices.spectrometer.options.lamp: "vis" there, "uv" here',
                     "chemistry.noise: 0.5 there, 0.01 here"]  # cost is the lab's books, not the device's doing
    assert differences(served_as(lab, "spectrometer"), served_as(lab, "spectrometer"), "spectrometer") == []
    # a device of another make reports no scenario: nothing to compare
    assert differences(served_as(lab, "spectrometer"), {}, "spectrometer") == []
    # a real instrument's options name what its host reaches it by (a broker, a port): not compared
    instrument = served_as(theirs, "spectrometer", instrument=True)
    assert "options" not in instrument["device_type"]
    assert not any(".options." in line for line in differences(served_as(lab, "spectrometer"), instrument,
                                                                  "spectrometer"))


def test_a_lab_of_several_campaigns_compares_the_devices_alone():
    shared = parse(yaml.safe_load((Path(__file__).resolve().parents[2] / "scenarios/shared_lab.yaml").read_text()))
    dtype = next(iter(shared.devices))
    assert set(served_as(shared, dtype)) == {"device_type"}


def test_each_external_device_that_joins_is_asked_once_and_one_served_alike_is_not_named(virtual_clock):
    lab = parse(qd_lab())
    theirs = parse(qd_lab(**{"devices.spectrometer.duration.mean_s": 600}))
    told: list = []

    async def main():
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        check = ServedCheck(bus, lab, virtual_clock, {"spectrometer-1", "spectrometer-2"},
                            lambda kind, device, detail: told.append((kind, device, detail))).start()
        actors = [DeviceActor("spectrometer-1", theirs.devices["spectrometer"], Reader(), bus, virtual_clock, lab.lab,
                              0, served_as=served_as(theirs, "spectrometer")),
                  DeviceActor("spectrometer-2", lab.devices["spectrometer"], Reader(), bus, virtual_clock, lab.lab, 0,
                              served_as=served_as(lab, "spectrometer")),
                  DeviceActor("synthesiser", theirs.devices["synthesiser"], Reader(), bus, virtual_clock, lab.lab, 0,
                              served_as=served_as(theirs, "synthesiser"))]  # in this process: not asked
        for a in actors:
            await a.start()
        await virtual_clock.sleep(60)
        await actors[0].stop()  # leaves and joins again: said once
        await actors[0].start()
        await virtual_clock.sleep(60)
        for a in actors:
            await a.stop()
        check.close()
        await bus.close()

    virtual_clock.run(main())
    assert told == [("device.mismatch", "spectrometer-1", {"type": "spectrometer", "more": 0, "differences": [
        "devices.spectrometer.duration.mean_s: 600.0 there, 60.0 here"]})]


def test_a_device_missing_here_and_on_the_bus_as_another_labs_is_named_when_the_lab_starts(virtual_clock):
    """A device served with a copy of the lab file whose `lab:` differs joins that lab: the lab only said it was
    missing. Another lab's device of the same name is no news while this lab's is here too."""
    lab = parse(qd_lab(**{"devices.spectrometer.instances": 3}))
    told: list = []

    async def main():
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        check = ServedCheck(bus, lab, virtual_clock, {"spectrometer-1", "spectrometer-2", "spectrometer-3"},
                            lambda kind, device, detail: told.append((kind, device, detail)), 100.0).start()
        spec = lab.devices["spectrometer"]
        actors = [DeviceActor("spectrometer-1", spec, Reader(), bus, virtual_clock, "t2", 0),  # the other lab's
                  DeviceActor("spectrometer-2", spec, Reader(), bus, virtual_clock, "t2", 0),
                  DeviceActor("spectrometer-2", spec, Reader(), bus, virtual_clock, lab.lab, 0)]  # and this one's
        for a in actors:
            await a.start()
        await virtual_clock.sleep(200)
        for a in actors:
            await a.stop()
        check.close()
        await bus.close()

    virtual_clock.run(main())
    assert told == [("device.elsewhere", "spectrometer-1", {"labs": ["t2"], "lab": "t"})]
    said = alert_text(Note(100.0, "device.elsewhere", device="spectrometer-1", detail=told[0][2]))
    assert said.startswith("device.elsewhere spectrometer-1: not on the bus as a device of lab 't', but on it as a "
                           "device of lab 't2'") and said.endswith("a device of your own puts lab 't' in its keys "
                                                                  "(docs/wire.md)"), said


@pytest.mark.parametrize("external,on_bus,told", [
    ({"spectrometer"}, ["spectrometer-1", "ghost"], {"spectrometer": ["spectrometer-1"]}),  # docs/mqtt.md's naming
    ({"spectrometer-1", "spectrometer-2"}, ["spectrometer-2", "spectromter-1"], {"spectrometer-1": ["spectromter-1"]}),
    ({"spectrometer"}, ["spectrometer", "spectrometer-1"], {})])  # the device is here: no news
def test_a_device_missing_while_a_name_like_its_own_is_on_the_labs_bus_is_named_with_it(virtual_clock, external,
                                                                                        on_bus, told):
    """A device of a stranger's, written from docs/wire.md for a lab of one spectrometer, declared
    `labtwin/t/alive/spectrometer-1`: the lab only said `spectrometer` was missing, and sent it nothing."""
    lab = parse(qd_lab(**{"devices.spectrometer.instances": len(external)}))
    said: list = []

    async def main():
        bus = open_bus("memory", virtual_clock)
        await bus.start()
        check = ServedCheck(bus, lab, virtual_clock, external,
                            lambda kind, device, detail: said.append((kind, device, detail)), 100.0).start()
        tokens = [bus.declare_token(f"labtwin/{lab.lab}/alive/{name}") for name in on_bus]
        await virtual_clock.sleep(200)
        for token in tokens:
            token.close()
        check.close()
        await bus.close()

    virtual_clock.run(main())
    assert said == [("device.misnamed", device, {"names": names, "lab": "t", "type": "spectrometer"})
                    for device, names in told.items()]
    if told:
        words = alert_text(Note(100.0, "device.misnamed", device=said[0][1], detail=said[0][2]))
        assert "no device of lab 't': a device of lab 't' named spectrometer" in words, words
        assert "declares labtwin/t/alive/spectrometer" in words and "docs/wire.md" in words, words


@pytest.mark.process
def test_a_device_served_from_an_edited_copy_of_the_lab_file_is_named_when_it_joins(tmp_path, caplog):
    router = f"tcp/127.0.0.1:{free_port()}"
    raw = qd_lab(**{"campaign.budget": 2, "devices.spectrometer.instances": 1,
                    "clock": {"mode": "scaled", "speed": SPEED}, "orchestrator.startup_s": 4000,
                    "bus": {"kind": "zenoh", "listen": [], "connect": [router]}})
    path = tmp_path / "lab.yaml"
    path.write_text(yaml.safe_dump(raw))
    (tmp_path / "device_host").mkdir()
    edited = tmp_path / "device_host" / "lab.yaml"  # the copy on the device's host, edited since
    raw["devices"]["spectrometer"]["duration"]["mean_s"] = 90
    edited.write_text(yaml.safe_dump(raw))
    s = prepare(path)
    clock = make_clock(s)
    procs = [start(["router", "--listen", router], "router"),
             start(["device", "serve", str(edited), "--id", "spectrometer", "--connect", router], "ready spectrometer")]
    try:
        with caplog.at_level(logging.WARNING, logger="twin.alerts"):
            summary = clock.run(run_async(s, clock, tmp_path / "j.db", {"spectrometer"}))
        (asked,) = health(path, ["spectrometer"], [router])  # `twin device health lab.yaml` says so too
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert summary.done == 2
    (event,) = read_events(tmp_path / "j.db", "device.mismatch")
    assert event["device"] == "spectrometer"
    assert json.loads(event["detail"])["differences"] == ["devices.spectrometer.duration.mean_s: 90.0 there, 60.0 here"]
    assert asked["differs"] == ["devices.spectrometer.duration.mean_s: 90.0 there, 60.0 here"]
    said = [r.getMessage() for r in caplog.records if r.name == "twin.alerts"]
    assert any(m.startswith("device.mismatch spectrometer: served by a process whose scenario differs") and
               "twin device serve LAB.yaml --id spectrometer" in m for m in said), said
