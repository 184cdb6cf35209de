#!/usr/bin/env bash
# Create (or update) the project's virtual environment with pinned versions of
# everything, then install the eleven bimacppo packages into it in editable mode.
#
#   scripts/install.sh            # venv at ./.venv
#   VENV=/opt/venv scripts/install.sh
#
# Idempotent: a second run only checks that everything is in place. The lock
# file pins transitive dependencies too, so a fresh machine gets what CI tested.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
PYTHON="${PYTHON:-python3.11}"

if ! command -v "$PYTHON" >/dev/null 2>&1; then
  echo "install.sh: $PYTHON not found. The ros-jazzy-* wheels target CPython 3.11; install it or set PYTHON=/path/to/python3.11." >&2
  exit 1
fi
if [ ! -x "$VENV/bin/python" ]; then
  echo ">> creating virtual environment at $VENV"
  "$PYTHON" -m venv "$VENV"
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check)
stamp="$VENV/.bimacppo-lock.sha256"
# _gymnasium_hook.py: its source is copied into a .pth at install time (bimacppo_learning/setup.py)
want="$(cat "$ROOT/requirements.lock" "$ROOT"/bimacppo_*/setup.py "$ROOT/scripts/install.sh" \
  "$ROOT/bimacppo_learning/bimacppo_learning/_gymnasium_hook.py" | sha256sum | cut -d' ' -f1)"
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  echo ">> environment up to date ($VENV)"
else
  echo ">> installing pinned dependencies (requirements.lock)"
  "${PIP[@]}" install -q --upgrade "pip>=24" "setuptools==79.0.1" wheel
  "${PIP[@]}" install -q -r "$ROOT/requirements.lock"
  echo ">> installing bimacppo packages (editable)"
  # compat mode = a .pth path entry per package: the repo root also holds same-named
  # ROS package folders, which an import-hook editable install would lose to.
  "${PIP[@]}" install -q --no-deps --no-build-isolation --config-settings editable_mode=compat \
    -e "$ROOT/bimacppo_common" -e "$ROOT/bimacppo_interfaces" -e "$ROOT/bimacppo_ros_common" \
    -e "$ROOT/bimacppo_bag" -e "$ROOT/bimacppo_sim" -e "$ROOT/bimacppo_mpc" \
    -e "$ROOT/bimacppo_curriculum" -e "$ROOT/bimacppo_planner" -e "$ROOT/bimacppo_learning" \
    -e "$ROOT/bimacppo_viz" -e "$ROOT/bimacppo_bringup"
  echo "$want" > "$stamp"
fi
"$VENV/bin/python" - <<'PY'
import importlib
for m in ("rclpy", "casadi", "torch", "gymnasium", "bimacppo_common", "bimacppo_interfaces.contract",
          "bimacppo_ros_common.runtime", "bimacppo_bag.recorder", "bimacppo_sim", "bimacppo_mpc",
          "bimacppo_curriculum", "bimacppo_planner", "bimacppo_learning", "foxglove", "bimacppo_viz",
          "bimacppo_bringup.composition"):
    importlib.import_module(m)
print(">> environment OK")
PY
