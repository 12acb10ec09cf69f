#!/usr/bin/env bash
# The demo: set up the workspace (if needed), then run the whole node graph (omni_driver replaying a
# recorded device session, sim_node, viz_node) headless with live one-line metrics; at the end of
# the bag the nodes stop and the viz report folder (plots, tables, summary) is printed.
# Extra arguments go to scripts/demo_run.py, e.g. `bash scripts/demo.sh --bag bags/sweep --mode lockstep`.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/setup.sh"
# shellcheck source=/dev/null
source "$ROOT/scripts/env.sh"
cd "$ROOT"
exec python scripts/demo_run.py "$@"
