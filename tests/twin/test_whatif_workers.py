"""`twin whatif`'s worker processes keep quiet: what a run's plan, driver or device would say is said once, by the
command, not by each of its runs (each test runs the command in a process of its own: the workers of one run in
this one write to their copies of the test's captured stream)."""

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_a_plan_is_told_once_by_the_command_not_by_every_workers_run(tmp_path):
    """Each worker's run of an rl scheduler that plans (campaign.local_search, campaign.rollouts) printed its two
    planning lines: 2 variants × 3 seeds buried the progress bar under a dozen of them. (A real process: the
    workers of one run in this one write to their copies of the test's captured stream.)"""
    import os
    import subprocess
    import sys

    shop = tmp_path / "la02.yaml"
    shop.write_text(f"name: la02\nlab: jobshop\njobshop: {{file: {ROOT / 'scenarios' / 'jobshop' / 'la02.txt'}}}\n"
                    f"campaign: {{scheduler: 'rl:{ROOT / 'agents' / 'policies' / 'jobshop_scheduler.zip'}'}}\n")
    done = subprocess.run([sys.executable, "-m", "twin", "whatif", str(shop), "--vary", "campaign.local_search=200,300",
                           "--seeds", "3"], capture_output=True, text=True, cwd=ROOT, timeout=120,
                          env={**os.environ, "COLUMNS": "80"})
    assert done.returncode == 0, done.stderr
    assert 1 <= done.stderr.count("rl: playing la02") <= 2, done.stderr  # the command's check of each plan it makes
    assert done.stderr.count("tabu-search swaps on its orders") == done.stderr.count("rl: playing la02")
    assert "300 " in done.stdout and "lab-s" in done.stdout


def test_a_driver_the_fast_runtime_cannot_run_is_said_once_by_the_command_not_by_every_run(tmp_path):
    """Every worker's run of a lab whose driver calls an SDK in a thread said that the fast runtime could not run
    it and that the campaign ran again on the asyncio runtime: 2 variants × 3 seeds printed it six times. The
    workers now hand it to the command, which says it once (for a lab of several campaigns too)."""
    import os
    import subprocess
    import sys

    import yaml

    from tests.twin.test_device_twins import sdk_lab

    single = tmp_path / "sdk.yaml"
    single.write_text(yaml.safe_dump(sdk_lab()))
    shared = yaml.safe_load((ROOT / "scenarios" / "shared_lab.yaml").read_text())
    shared["devices"]["spectrometer"]["driver"] = "tests.twin.test_runtimes:MeasuresAfterIo"
    for c, budget in zip(shared["campaigns"], (4, 3)):
        c["campaign"]["budget"] = budget
    (tmp_path / "shared.yaml").write_text(yaml.safe_dump(shared))
    for lab, vary in ((single, "devices.synthesiser.instances=1,2"), (tmp_path / "shared.yaml",
                                                                      "devices.reactor.instances=1,2")):
        done = subprocess.run([sys.executable, "-m", "twin", "whatif", str(lab), "--vary", vary, "--seeds", "3"],
                              capture_output=True, text=True, cwd=ROOT, timeout=180, env={**os.environ, "COLUMNS": "80"})
        assert done.returncode == 0, done.stderr
        assert done.stderr.count("awaited an asyncio future") == 1, done.stderr
        assert "on the asyncio runtime" in done.stderr and "*: the scenario as written" in done.stdout
    # an instrument whose link drops: each run on the asyncio runtime logged its device warnings ("instrument gone",
    # 41 lines for 2 variants x 10 seeds), where the fast runtime's runs keep theirs in the workers
    from tests.conftest import qd_lab

    flickering = tmp_path / "flickering.yaml"
    flickering.write_text(yaml.safe_dump(qd_lab(**{
        "devices.spectrometer.driver": "tests.twin.test_instrument_links:Flickering"})))
    done = subprocess.run([sys.executable, "-m", "twin", "whatif", str(flickering), "--vary",
                           "devices.spectrometer.instances=2,3", "--seeds", "3"], capture_output=True, text=True,
                          cwd=ROOT, timeout=180, env={**os.environ, "COLUMNS": "80"})
    assert done.returncode == 0, done.stderr
    assert "instrument gone" not in done.stderr and "*: the scenario as written" in done.stdout, done.stderr
    said = " ".join(done.stderr.split())
    assert said.count("connects to an instrument of its own") == 1, said
    assert "devices.spectrometer.twin: {driver: NAME}" in said and "twin run --runtime asyncio starts there" in said
