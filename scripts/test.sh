#!/usr/bin/env bash
# The project's test command (README, second command; .ci/run calls this).
# Installs the pinned environment if needed, then runs the test suite.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` or `scripts/test.sh tests/test_sim_world.py`.
set -uo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$ROOT/scripts/install.sh" || exit $?
cd "$ROOT"
export AMENT_PREFIX_PATH="${VENV:-$ROOT/.venv}${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
"${VENV:-$ROOT/.venv}/bin/python" -m pytest "$@"
rc=$?
# pytest exits 5 when it collected no test: that is a failure of the suite, not a pass.
if [ $rc -eq 5 ]; then echo "test.sh: pytest collected no tests" >&2; exit 1; fi
exit $rc
