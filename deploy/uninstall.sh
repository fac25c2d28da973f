#!/usr/bin/env bash
# Remove what deploy/install.sh put on a robot. Run as root:
#   sudo deploy/uninstall.sh            # the unit, /opt/mapd, mapd on the PATH
#   sudo deploy/uninstall.sh --purge    # and the config and keys (/etc/mapd), the maps and state
#                                       # (/var/lib/mapd), the udev rule, the compiled kernels and
#                                       # the mapd user
# Without --purge the robot's identity stays: its key, its config and its maps, which a later
# install.sh takes up again as they were (the fleet knows the robot by that key).
set -euo pipefail
purge=no
case "${1:-}" in
  "") ;;
  --purge) purge=yes ;;
  *) echo "usage: $0 [--purge]" >&2; exit 2 ;;
esac
[ "$(id -u)" = 0 ] || { echo "uninstall.sh must run as root" >&2; exit 1; }

# stopped first: a stop saves the state (TimeoutStopSec gives it the time)
systemctl disable --now mapd 2>/dev/null || true
rm -f /etc/systemd/system/mapd.service
rm -rf /etc/systemd/system/mapd.service.d   # drop-ins made with systemctl edit mapd
systemctl daemon-reload 2>/dev/null || true
systemctl reset-failed mapd 2>/dev/null || true
# the link on the PATH only where it is install.sh's (another mapd there is left alone)
if [ "$(readlink /usr/local/bin/mapd 2>/dev/null)" = /opt/mapd/venv/bin/mapd ]; then
  rm -f /usr/local/bin/mapd
fi
rm -rf /opt/mapd
if [ "$purge" = yes ]; then
  rm -rf /etc/mapd /var/lib/mapd /var/cache/mapd /run/mapd
  # the udev rule too: edited to this robot's radio, it is kept for a later install otherwise
  rm -f /etc/udev/rules.d/99-mapd-uwb.rules
  udevadm control --reload 2>/dev/null || true
  if id mapd >/dev/null 2>&1; then userdel mapd; fi
  echo "mapd removed, with its config, keys, maps and user"
else
  echo "mapd removed; kept: /etc/mapd (config, keys), /var/lib/mapd (maps, state), the udev rule, the mapd user" \
       "(sudo deploy/uninstall.sh --purge removes them too)"
fi
