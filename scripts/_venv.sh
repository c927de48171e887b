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
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[dev,bench]'
  rm -f .venv/.labtwin-*
  touch "$stamp"
fi
export PATH="$PWD/.venv/bin:$PATH"
