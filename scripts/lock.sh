#!/usr/bin/env bash
# Regenerates constraints.txt: the exact versions a fresh install of the package and its test extras
# resolves to today (pip freeze of a new virtual environment, minus the project itself).
# scripts/install.sh and the Dockerfile install with `-c constraints.txt`, so every install matches.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
"$tmp/venv/bin/python" -m pip install -q --disable-pip-version-check -e '.[test]'
{
  echo "# Pinned versions for every install (pip install -c constraints.txt ...): the set a fresh"
  echo "# environment resolved to on $(date -u +%Y-%m-%d) with $("$tmp/venv/bin/python" -V)."
  echo "# Regenerate with: bash scripts/lock.sh"
  "$tmp/venv/bin/python" -m pip freeze --disable-pip-version-check --exclude-editable | grep -v -i '^gyrobench[= @]' | LC_ALL=C sort -f
} > constraints.txt.tmp
mv constraints.txt.tmp constraints.txt
echo "constraints.txt: $(grep -vc '^#' constraints.txt) pinned packages"
