#!/usr/bin/env bash
# Refresh the lock file: install esmm with its dev extras into a throw-away venv, taking the
# newest releases pyproject.toml allows, and freeze what was installed (esmm itself excluded).
# Usage: scripts/lock.sh PYTHON OUT       (what `make lock` runs)
# Then run `make test` on the new lock before committing it.
set -euo pipefail
python=${1:-python3}
out=${2:-requirements.lock}
here=$(cd "$(dirname "$0")/.." && pwd)
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$python" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --quiet --upgrade pip
"$tmp/venv/bin/python" -m pip install --quiet "$here[dev]"
{
  echo "# The dependency versions esmm is tested with (pip constraints; see README, 'Environment')."
  echo "# make demo / make test install from it. Refresh: make lock (then make test, then commit)."
  echo "# Python $("$tmp/venv/bin/python" -c 'import platform; print(platform.python_version())'), $(uname -m), $(date -u +%Y-%m-%d)."
  "$tmp/venv/bin/python" -m pip freeze --all --exclude-editable | grep -v -i -E '^(esmm|pip|setuptools|wheel)[=@ ]'
} > "$out.new"
mv "$out.new" "$out"
echo "wrote $out ($(grep -c '==' "$out") pins)"
