# Sourced by scripts/run and scripts/test: create or reuse .venv and install
# the project into it when pyproject.toml has changed since the last install.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "labtwin: creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
stamp=".venv/.labtwin-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "labtwin: installing labtwin and its dependencies into .venv (a few minutes the first time)" >&2
  # torch comes in the same pip command as stable-baselines3, pinned to the CPU build on disk
  # pip compiles every module it installs on one core (~80 s of 2.5 min here); compileall does it on all cores
  .venv/bin/python -m pip install --quiet --no-compile --disable-pip-version-check -e '.[dev,bench]'
  .venv/bin/python -m compileall -q -j 0 "$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" > /dev/null || true
  rm -f .venv/.labtwin-*
  touch "$stamp"
fi
# the project's own bytecode, where PYTHONDONTWRITEBYTECODE would have every process compile it again
# (~0.25 s of each `twin` start); a file that does not compile is left for Python to report when imported
.venv/bin/python -m compileall -q -j 0 twin agents devices bench > /dev/null 2>&1 || true
export PATH="$PWD/.venv/bin:$PATH"
