# Sourced by scripts/run and scripts/test: create or reuse .venv and install
# the project into it when pyproject.toml has changed since the last install.
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
PY=${PYTHON:-python3}
# one set-up at a time: scripts/run and scripts/test started together on a fresh clone each made and filled .venv
# at once, and one of them failed ("No module named pip"); the other waits here, then finds it made
mkdir -p .venv
if command -v flock > /dev/null; then
  exec 9> .venv/.setup.lock
  if ! flock -n 9; then
    echo "labtwin: waiting for another set-up of .venv to finish" >&2
    flock 9
  fi
fi
if [ ! -x .venv/bin/python ]; then
  echo "labtwin: creating .venv with $($PY --version)" >&2
  "$PY" -m venv .venv
fi
stamp=".venv/.labtwin-$(sha256sum pyproject.toml | cut -c1-16)"
if [ ! -f "$stamp" ]; then
  echo "labtwin: installing labtwin and its dependencies into .venv (about a minute the first time)" >&2
  # torch comes in the same command as stable-baselines3, pinned to the CPU build on disk. uv, given pip's
  # indexes, wheels and caps, installs in ~20 s what pip takes ~65 s for; pip is the fallback
  if .venv/bin/python -m pip install --quiet --disable-pip-version-check uv > /dev/null 2>&1 &&
      pip_config=$(.venv/bin/python scripts/_uv_args.py) && mapfile -t uv_args <<< "$pip_config" &&
      cert=${uv_args[0]:-${SSL_CERT_FILE:-}} &&
      env ${cert:+SSL_CERT_FILE="$cert"} .venv/bin/uv pip install --quiet --python .venv/bin/python \
        --index-strategy unsafe-best-match "${uv_args[@]:1}" -e '.[dev,bench]'; then
    :
  else
    echo "labtwin: installing with pip instead of uv" >&2
    .venv/bin/python -m pip install --quiet --no-compile --disable-pip-version-check -e '.[dev,bench]'
  fi
  # compiled here, on every core, for where PYTHONDONTWRITEBYTECODE is set (every process would compile what it
  # imports again); the libraries' own tests, never imported, are a quarter of the files (~40 s -> ~28 s here)
  .venv/bin/python -m compileall -q -j 0 -x '/tests?/' "$(.venv/bin/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')" > /dev/null || true
  rm -f .venv/.labtwin-*
  touch "$stamp"
fi
# the project's own bytecode, where PYTHONDONTWRITEBYTECODE would have every process compile it again
# (~0.25 s of each `twin` start); a file that does not compile is left for Python to report when imported
.venv/bin/python -m compileall -q -j 0 twin agents devices bench > /dev/null 2>&1 || true
exec 9>&-
export PATH="$PWD/.venv/bin:$PATH"
