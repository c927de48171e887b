"""`twin driver new` makes a package that pip-installs, is discovered, passes its own tests and runs a campaign."""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest


ROOT = Path(__file__).resolve().parents[2]
TWIN = [sys.executable, "-m", "twin"]
PIP = [sys.executable, "-m", "pip", "--disable-pip-version-check", "--quiet"]


def sh(args, **kw):
    return subprocess.run(args, capture_output=True, text=True, timeout=300, **kw)


def test_a_scaffolded_driver_installs_and_runs_unmodified(tmp_path):
    made = sh([*TWIN, "driver", "new", "acme-hplc", "--dir", str(tmp_path)], cwd=ROOT)
    assert made.returncode == 0, made.stderr
    pkg = tmp_path / "acme-hplc"
    driver = (pkg / "acme_hplc" / "driver.py").read_text()
    assert len(driver.splitlines()) < 50
    installed = sh([*PIP, "install", "--no-deps", "--no-build-isolation", "-e", str(pkg)])
    assert installed.returncode == 0, installed.stderr
    try:
        listed = sh([*TWIN, "devices"], cwd=ROOT, env={**os.environ, "COLUMNS": "200"})
        assert "acme-hplc" in listed.stdout and "acme_hplc.driver:AcmeHplc" in listed.stdout
        own_tests = sh([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(pkg / "tests")], cwd=pkg)
        assert own_tests.returncode == 0 and "3 passed" in own_tests.stdout, own_tests.stdout + own_tests.stderr
        assert "Warning" not in own_tests.stdout + own_tests.stderr  # a stranger's first run is a clean one
        campaign = sh([*TWIN, "run", str(pkg / "scenario.yaml"), "--json", "--journal", str(tmp_path / "j.db")], cwd=ROOT)
        assert campaign.returncode == 0, campaign.stderr
        assert '"done": 4' in campaign.stdout
    finally:
        sh([*PIP, "uninstall", "-y", "acme-hplc"])


def test_bad_names_and_existing_directories_are_refused(tmp_path):
    bad = sh([*TWIN, "driver", "new", "Acme HPLC", "--dir", str(tmp_path)], cwd=ROOT)
    assert bad.returncode == 2 and "lower-case letters" in bad.stderr
    (tmp_path / "acme").mkdir()
    again = sh([*TWIN, "driver", "new", "acme", "--dir", str(tmp_path)], cwd=ROOT)
    assert again.returncode == 2 and "already exists" in again.stderr


@pytest.mark.parametrize("name, says", [
    ("twin", "its Python module would be twin, which is importable here already"),  # it shadowed labtwin's kernel
    ("numpy", "the package numpy"),  # `pip install -e numpy` would have replaced numpy
    ("labtwin", "`pip install` of this one would replace it"),
    ("spectrometer", "an installed driver is called so"),  # two entry points of one name
    ("operator", "`driver: operator` means people"),
])
def test_a_name_that_would_clash_with_what_is_installed_is_refused(tmp_path, name, says):
    from twin.core.errors import TwinError
    from twin.tools.scaffold import scaffold

    with pytest.raises(TwinError, match=rf"driver name '{name}' is taken: .*{re.escape(says)}.*; choose another, "
                                        rf"e.g. acme-{name}"):
        scaffold(name, tmp_path)
    assert not any(tmp_path.iterdir())  # nothing written
