#!/usr/bin/env bash
# probecal set-up and launcher: installs whatever is missing, then runs the given action.
#   ./run.sh serve [ARGS...]   start the console on the built-in simulator (http://127.0.0.1:8080)
#   ./run.sh lint              ruff and mypy, stopping at the first that fails (a minute at most)
#   ./run.sh test  [ARGS...]   the lint stage, then the test suite (pytest arguments may follow)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

action=${1:-}
case "$action" in
  serve|lint|test) shift ;;
  *) echo "usage: ./run.sh serve|lint|test [ARGS...]" >&2; exit 2 ;;
esac

# Debian packages: open3d needs libusb at import time; the browser tests need chromium.
missing=()
ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
if [[ $action == test && ! -x /usr/bin/chromium ]]; then missing+=(chromium); fi
if ((${#missing[@]})); then
  echo "run.sh: installing Debian packages: ${missing[*]}" >&2
  sudo=""; [[ $(id -u) == 0 ]] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# Python virtual environment in .venv, reinstalled when pyproject.toml changes.
python=${PYTHON:-python3}
if [[ ! -x .venv/bin/python ]]; then
  echo "run.sh: creating .venv" >&2
  "$python" -m venv .venv
fi
stamp=.venv/.probecal-installed
want=$(sha256sum pyproject.toml | cut -d' ' -f1)
if [[ ! -f $stamp || $(cat "$stamp") != "$want" ]]; then
  echo "run.sh: installing probecal and its dependencies into .venv" >&2
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q -e '.[test]'
  echo "$want" > "$stamp"
fi

# The lint stage: ruff, then mypy on the packages by their installed names (pyproject's [tool.mypy]).
lint() {
  echo "run.sh: ruff" >&2
  .venv/bin/ruff check core app tests benchmarks
  echo "run.sh: mypy" >&2
  .venv/bin/mypy
}

case "$action" in
  serve) exec .venv/bin/probecal serve "$@" ;;
  lint) lint ;;
  test) lint; exec .venv/bin/python -m pytest "$@" ;;  # set -e: a failing lint ends the run here
esac
