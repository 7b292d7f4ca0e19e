#!/usr/bin/env bash
# Set up .venv (see setup_env.sh) and run the end-to-end demo on synthetic data.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$(bash "$root/scripts/setup_env.sh" | tail -n 1)"
export PATH="$venv/bin:$PATH"
exec "$venv/bin/python" -m magcal_ros.app.demo "$@"
