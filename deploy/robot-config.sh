#!/usr/bin/env bash
# The example config.toml made into one robot's /etc/mapd/config.toml (install.sh runs it):
#   deploy/robot-config.sh ROBOT FLEET < config.toml > /etc/mapd/config.toml
# It names the robot and its fleet, points the keys at /etc/mapd and the paper codec's models at
# /opt/mapd/models (the unit's MAPD_MODELS, which a shell lacks), and drops the example's
# placeholder roster lines (install.sh adds the robot's own). Every other line is kept as it is:
# the example's state, runtime and output folders are the unit's (StateDirectory, RuntimeDirectory).
set -euo pipefail
[ $# -eq 2 ] || { echo "usage: $0 ROBOT FLEET < config.toml" >&2; exit 2; }
robot="$1"; fleet="$2"
for v in "$robot" "$fleet"; do
  # mapd's own rule for robot and fleet names (config.NAME_PATTERN)
  [[ "$v" =~ ^[A-Za-z0-9_-]{1,32}$ ]] || { echo "$0: '$v': 1 to 32 letters, digits, _ and - only" >&2; exit 2; }
done
sed -e "s/^name = \"alpha\"/name = \"$robot\"/" -e "s/^fleet = \"demo\"/fleet = \"$fleet\"/" \
    -e 's#^key_file = .*#key_file = "/etc/mapd/robot.key"#' \
    -e 's#^link_key_file = .*#link_key_file = "/etc/mapd/link.key"#' \
    -e 's@^# model_dir = "/opt/mapd/models".*@model_dir = "/opt/mapd/models"   # where install.sh put them (mapd in a shell reads this file too)@' \
    -e '/^[A-Za-z0-9_-]* = "ed25519:A*="/d'
