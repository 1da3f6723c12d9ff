#!/usr/bin/env bash
# probecal set-up and launcher: installs whatever is missing, then runs the given action.
#   ./run.sh serve [ARGS...]   start the console on the built-in simulator (http://127.0.0.1:8080)
#   ./run.sh test  [ARGS...]   run the test suite (pytest arguments may follow)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")"

action=${1:-}
case "$action" in
  serve|test) shift ;;
  *) echo "usage: ./run.sh serve|test [ARGS...]" >&2; exit 2 ;;
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

case "$action" in
  serve) exec .venv/bin/probecal serve "$@" ;;
  test) exec .venv/bin/python -m pytest "$@" ;;
esac
