"""The same alert, again and again, is said in full a few times and then by its count in virtual time; on a live
clock every one is said (a person may have to act on it); the journal keeps all of them either way."""

import logging
from pathlib import Path

from twin.campaign.events import Note
from twin.campaign.journal_read import read_events
from twin.runtime.alert_log import IN_FULL, AlertLog
from twin.runtime.lab import make_clock, run, run_async
from twin.scenario import parse

from tests.conftest import qd_lab

ROOT = Path(__file__).resolve().parents[2]


def test_a_lab_whose_steps_all_fail_says_each_alert_a_few_times_then_by_its_count(tmp_path, caplog):
    db = tmp_path / "j.db"
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        run(ROOT / "scenarios" / "quantum_dots.yaml", journal=db, bus="memory",
            overrides={"devices.synthesiser.faults.fail_p": 1.0, "campaign.budget": 60})
    said = [r.getMessage() for r in caplog.records if r.name == "twin.alerts"]
    journalled = [e for e in read_events(db) if e["kind"] == "devices.unavailable"]
    assert len(journalled) >= 10  # every one is in the journal
    assert len(said) == IN_FULL + (1 if len(journalled) >= 10 else 0) + (1 if len(journalled) >= 100 else 0), said
    assert all(s.startswith("devices.unavailable synthesiser: no synthesiser is usable") for s in said)
    assert said[IN_FULL].endswith("(the 10th time; said again at the 100th, and the journal has every one)")


def test_on_a_live_clock_every_alert_is_said(caplog):
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        live, virtual = AlertLog(virtual=False), AlertLog()
        for t in range(12):
            note = Note(float(t), "consumable.depleted", device="vials", detail={"item": "vials", "needed": 1})
            live(note)
            virtual(note)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 12 + IN_FULL + 1 and sum("vials is out" in s for s in said) == len(said)


def test_on_a_live_clock_a_device_gone_from_the_bus_is_said_and_its_return_with_how_long_it_was_away(caplog):
    """A device whose process died was said nowhere until the summary (the journal had it): on a live clock a
    person may have a process to restart. Its first arrival is no news, and in virtual time a crash is the model's."""
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        for log in (AlertLog(virtual=False), AlertLog()):
            log.presence(Note(0.0, "device.online", device="kiln-2"))
            log.presence(Note(100.0, "device.lost", device="kiln-2"))
            log.presence(Note(160.0, "device.online", device="kiln-2"))
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2, said
    assert said[0].startswith("device.lost kiln-2: left the bus")
    assert "serve` that ended must be started again" in said[0]
    assert said[1] == "device.online kiln-2: back on the bus after 60 lab-s away; it is given work again"


def test_on_a_live_clock_a_device_type_said_unusable_is_said_usable_again(caplog):
    """A quarantined spectrometer probed back to work had been said unusable again and again, and never usable."""
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        for log in (AlertLog(virtual=False), AlertLog()):
            log.presence(Note(500.0, "devices.available", device="spectrometer", detail={"type": "spectrometer"}))
    said = [r.getMessage() for r in caplog.records]
    assert said == ["devices.available spectrometer: one can take work again (back on the bus, or a quarantined one "
                    "given a step to try it), and the work waiting for it goes on"]


def test_on_a_live_clock_a_device_whose_type_simulates_crashes_is_said_to_have_crashed(caplog):
    """flaky_lab on a scaled clock said of each simulated crash that a `twin device serve` may need starting again."""
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        log = AlertLog(virtual=False, crashing={"reactor-1": ("reactor", 3600.0)})
        log.presence(Note(100.0, "device.lost", device="reactor-1"))
        log.presence(Note(3700.0, "device.online", device="reactor-1"))
    said = [r.getMessage() for r in caplog.records]
    assert said[0].startswith("device.lost reactor-1: crashed, as devices.reactor.faults.mtbc_h simulates (back after "
                              "faults.restart_s, 3600 lab-s)") and "twin device serve" not in said[0]
    assert said[1] == "device.online reactor-1: back on the bus after 3600 lab-s away; it is given work again"


def test_a_simulated_crash_on_a_scaled_clock_is_said_as_one_and_counted_as_one(tmp_path, caplog):
    s = parse(qd_lab(**{"devices.synthesiser.faults": {"mtbc_h": 0.05, "restart_s": 100},
                        "clock": {"mode": "scaled", "speed": 2000.0}}))
    clock = make_clock(s)
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        summary = clock.run(run_async(s, clock, tmp_path / "j.db"))
    lost = [r.getMessage() for r in caplog.records if r.getMessage().startswith("device.lost")]
    assert summary.devices_lost and len(lost) == len(read_events(tmp_path / "j.db", "device.lost"))
    # each a loss: the memory bus has no links to flap (at 2000x a lease is 2,000 lab-s, and crashes 100 lab-s
    # apart were taken for flaps, their steps left to time out)
    assert summary.devices_lost == len(lost) and not read_events(tmp_path / "j.db", "device.flapping")
    assert all(m.startswith("device.lost synthesiser: crashed, as devices.synthesiser.faults.mtbc_h simulates")
               for m in lost), lost


def test_on_a_live_clock_a_device_set_aside_for_failing_is_said(caplog):
    """One of four reactors quarantined was said nowhere on a live clock (only all four out was): a person may have
    it to mend."""
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        for log in (AlertLog(virtual=False), AlertLog()):
            log.presence(Note(100.0, "device.quarantined", device="reactor-2", detail={"probe_after_s": 3600.0}))
    (said,) = [r.getMessage() for r in caplog.records]
    assert said.startswith("device.quarantined reactor-2: set aside after failing step after step "
                           "(orchestrator.quarantine_after)") and said.endswith("probe_after_s, 3600 lab-s")


def test_a_person_set_aside_is_said_to_be_so_for_steps_nobody_confirmed(caplog):
    """A technician quarantined because nobody confirmed their steps was said to have failed "step after step", as a
    broken instrument is: found running a lab with a person on a scaled clock."""
    with caplog.at_level(logging.WARNING, logger="twin.alerts"):
        AlertLog(virtual=False, people=frozenset({"tech"})).presence(
            Note(100.0, "device.quarantined", device="tech", detail={"probe_after_s": 3600.0}))
    (said,) = [r.getMessage() for r in caplog.records]
    assert said.startswith("device.quarantined tech: set aside after its steps went unconfirmed in time, one after "
                           "another (orchestrator.quarantine_after)"), said
