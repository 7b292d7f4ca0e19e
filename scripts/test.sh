#!/usr/bin/env bash
# Set up .venv (see setup_env.sh) and run the test suite. Extra arguments go to pytest.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$(bash "$root/scripts/setup_env.sh" | tail -n 1)"
cd "$root"
export PATH="$venv/bin:$PATH"
# Small matrices: one BLAS thread each, so parallel test processes do not thrash two cores.
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}" OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
# DDS stays on this machine; the tests lease their own domains, never this environment's ROS_DOMAIN_ID.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# Test files run in parallel (pytest-xdist, one file per worker at a time, module fixtures kept):
# most of the time is spent waiting on node processes and replays, so two workers on two cores take about
# half the serial time (three took a third, but with two busy loops beside them the node processes of three
# files at once starved one another and a DDS test failed now and then). MAGCAL_TEST_WORKERS=0 runs serially.
# Lint first (rules in ruff.toml: pyflakes, bugbear, McCabe complexity 15 for the package): a finding fails fast.
"$venv/bin/ruff" check --quiet "$root" || { echo "ruff found the problems above (rules: ruff.toml)" >&2; exit 1; }
workers="${MAGCAL_TEST_WORKERS:-2}"
parallel=()
[ "$workers" != 0 ] && parallel=(-n "$workers" --dist loadfile)
exec "$venv/bin/python" -m pytest -q --durations=15 ${parallel[@]+"${parallel[@]}"} test "$@"
