#!/usr/bin/env bash
# Regenerate requirements.lock from the current .venv.
#
# Why a script: the ros-jazzy-* wheels ship both a dist-info (e.g. ros_std_msgs)
# and a legacy egg-info for the ROS package inside it (std_msgs). `pip freeze`
# lists the egg-info names as if they were distributions, but no index has
# them, so a lock with `std_msgs==5.3.6` cannot be installed on a fresh machine.
# We drop every name that exists only as an egg-info, and our own packages.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${VENV:-$ROOT/.venv}"
SITE="$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
egg_only="$(cd "$SITE" && ls -d *.egg-info 2>/dev/null | sed -E 's/-[0-9].*//' | tr 'A-Z-' 'a-z_' || true)"
"$VENV/bin/python" -m pip freeze --exclude-editable | grep -v -i '^bimacppo' | while IFS= read -r line; do
  name="$(printf '%s' "${line%%==*}" | tr 'A-Z-' 'a-z_')"
  if printf '%s\n' $egg_only | grep -qx "$name"; then continue; fi
  printf '%s\n' "$line"
done | sed -E "s/^(torch==[0-9.]+)\+cpu$/\1/" > "$ROOT/requirements.lock.new"
mv "$ROOT/requirements.lock.new" "$ROOT/requirements.lock"
echo "requirements.lock: $(wc -l < "$ROOT/requirements.lock") pins"
