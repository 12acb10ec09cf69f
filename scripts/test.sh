#!/usr/bin/env bash
# Set up the workspace (if needed) and run every test: core, nodes in real processes, system tests.
# Extra arguments go to pytest, e.g. `bash scripts/test.sh -k replay -x`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
# shellcheck source=/dev/null
source "$ROOT/scripts/env.sh"
cd "$ROOT"
set +e
python -m pytest --durations=15 "$@"
rc=$?
set -e
if [[ $rc == 5 ]]; then
  echo "test.sh: error: pytest collected no tests" >&2
fi
exit $rc
