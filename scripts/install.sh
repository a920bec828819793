#!/usr/bin/env bash
# Installs everything the product and its tests need on a fresh Debian machine with Python 3.11:
# Debian tools used by the tests (mbpoll, socat) and a virtual environment in .venv with the package,
# its test extras and the versions pinned in constraints.txt.
set -euo pipefail
cd "$(dirname "$0")/.."

need_apt=()
command -v mbpoll >/dev/null 2>&1 || need_apt+=(mbpoll)
command -v socat  >/dev/null 2>&1 || need_apt+=(socat)
command -v chromium >/dev/null 2>&1 || need_apt+=(chromium chromium-driver)   # dashboard browser tests
if [ ${#need_apt[@]} -gt 0 ]; then
  if [ "$(id -u)" = "0" ]; then SUDO=""; else SUDO="sudo"; fi
  # another apt/dpkg process (unattended upgrades, a second install) may hold the lock: wait for it
  # up to APT_LOCK_WAIT_S seconds (default 300) instead of failing at once
  lock_wait=${APT_LOCK_WAIT_S:-300}
  $SUDO apt-get -o DPkg::Lock::Timeout="$lock_wait" update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get -o DPkg::Lock::Timeout="$lock_wait" install -y -qq "${need_apt[@]}" >/dev/null
fi

PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip 2>/dev/null || true
# exact versions from constraints.txt (regenerate with scripts/lock.sh): two installs a month apart match
.venv/bin/python -m pip install -q --disable-pip-version-check -c constraints.txt -e '.[test]'
.venv/bin/python -c "import bench, pymodbus, sqlalchemy, numpy" 
