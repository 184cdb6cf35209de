#!/usr/bin/env bash
# The main job (README, first command): on a fresh machine, install the pinned
# environment, colcon-build the ROS 2 workspace, run the whole node graph
# (world, planner with the shipped policy, controller, curriculum, MCAP recorder)
# for a few episodes in lockstep, and print success / collision / timeout and
# where the recording is.
#
#   scripts/demo.sh                      # 6 episodes, n_sv and task chosen by the curriculum
#   EPISODES=12 scripts/demo.sh
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
bash "$ROOT/scripts/install.sh"
# shellcheck disable=SC1091
source "$VENV/bin/activate"
export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
export ROS_AUTOMATIC_DISCOVERY_RANGE="${ROS_AUTOMATIC_DISCOVERY_RANGE:-LOCALHOST}"
export ROS_DOMAIN_ID="${ROS_DOMAIN_ID:-$((100 + $$ % 100))}"
echo ">> colcon build (ros2_ws)"
(cd "$ROOT/ros2_ws" && colcon build > "$ROOT/ros2_ws/colcon-build.log" 2>&1) || { echo "colcon build failed: see ros2_ws/colcon-build.log" >&2; exit 1; }
# colcon's setup scripts read unset variables: relax -u while sourcing
set +u
# shellcheck disable=SC1091
source "$ROOT/ros2_ws/install/setup.bash"
set -u
OUT="${OUT:-$ROOT/runs/demo-$(date +%Y%m%d-%H%M%S)}"
echo ">> running the node graph (lockstep), recording to $OUT"
mkdir -p "$OUT"
exec bimacppo-graph --episodes "${EPISODES:-6}" --output "$OUT/demo.mcap" "$@"
