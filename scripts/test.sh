#!/usr/bin/env bash
# Set up the workspace (if needed) and run every test: core, nodes in real processes, system tests.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -k replay -x`. The tests run in
# TEST_WORKERS processes (default 2, pytest-xdist; 0 runs them in this process).
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
# shellcheck source=/dev/null
source "$ROOT/scripts/env.sh"
cd "$ROOT"
set +e
workers="${TEST_WORKERS:-2}"
if [[ "$workers" == 0 ]]; then
  python -m pytest --durations=15 "$@"
else
  python -m pytest -n "$workers" --dist loadfile --durations=15 "$@"
fi
rc=$?
set -e
if [[ $rc == 5 ]]; then
  echo "test.sh: error: pytest collected no tests" >&2
fi
exit $rc
