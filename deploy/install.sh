#!/usr/bin/env bash
# Install mapd on a robot: a venv under /opt/mapd, config and keys under /etc/mapd, the systemd unit,
# the udev rule, and a dedicated 'mapd' user in the 'dialout' group. Run as root from the repo root:
#   sudo deploy/install.sh [--robot NAME] [--fleet NAME] [--link-key FILE]
# The robot gets its own signing key (/etc/mapd/robot.key); the line printed for it goes into
# [fleet.roster] on every robot. --link-key copies the fleet's uwb link key (made once per fleet);
# without it, the first robot makes one to copy to the others.
set -euo pipefail
robot="$(hostname -s)"; fleet="default"; link_key=""
while [ $# -gt 0 ]; do
  case "$1" in
    --robot) robot="$2"; shift 2 ;;
    --fleet) fleet="$2"; shift 2 ;;
    --link-key) link_key="$2"; shift 2 ;;
    *) echo "usage: $0 [--robot NAME] [--fleet NAME] [--link-key FILE]" >&2; exit 2 ;;
  esac
done
# from where it was typed, before the cd below (a relative path meant the repo's folder)
if [ -n "$link_key" ]; then
  link_key="$(realpath -e -- "$link_key")" || { echo "--link-key: no such file" >&2; exit 2; }
fi
cd "$(dirname "$0")/.."
[ "$(id -u)" = 0 ] || { echo "install.sh must run as root" >&2; exit 1; }
# names first (a hostname with a dot is no robot name): nothing is installed with one mapd refuses
deploy/robot-config.sh "$robot" "$fleet" < /dev/null > /dev/null
py="$(command -v python3.11 || command -v python3)"
"$py" -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "mapd needs Python 3.11+")'

# --user-group: Group=mapd and install -g mapd need it where useradd makes no group by default
id mapd >/dev/null 2>&1 || useradd --system --user-group --home-dir /var/lib/mapd --shell /usr/sbin/nologin mapd
usermod -aG dialout mapd

install -d -m 0755 /opt/mapd
"$py" -m venv /opt/mapd/venv
links=""; [ -d /opt/wheels ] && links="--find-links /opt/wheels"
# with the ROS 2 plugins and recordings (a few small wheels): a robot's config may turn them on
/opt/mapd/venv/bin/pip install -q -c constraints.txt $links '.[ros2,record]'
rm -rf /opt/mapd/models && cp -r models /opt/mapd/models
cp README.md /opt/mapd/README.md
# `mapd status` and the rest on the PATH, as the README types them
ln -sfn /opt/mapd/venv/bin/mapd /usr/local/bin/mapd

install -d -m 0750 -o root -g mapd /etc/mapd
if [ ! -f /etc/mapd/config.toml ]; then
  # written whole or not at all: a half-written file would be kept by the next run
  deploy/robot-config.sh "$robot" "$fleet" < config.toml > /etc/mapd/config.toml.new
  mv /etc/mapd/config.toml.new /etc/mapd/config.toml
  chgrp mapd /etc/mapd/config.toml && chmod 0640 /etc/mapd/config.toml
  echo "wrote /etc/mapd/config.toml for robot '$robot' (edit it, then: systemctl restart mapd)"
fi
# Signed by default: this robot's own key, its line in the roster, and the fleet's uwb link key.
if [ ! -f /etc/mapd/robot.key ]; then
  line="$(/opt/mapd/venv/bin/mapd keygen "$robot" -o /etc/mapd/robot.key)"
  chgrp mapd /etc/mapd/robot.key && chmod 0640 /etc/mapd/robot.key
  # this robot's line replaced, not added beside an old one (a key made again): TOML refuses a key
  # given twice, and the daemon would not start
  sed -i "/^\[fleet.roster\]/,/^\[/{/^$robot[[:space:]]*=/d}" /etc/mapd/config.toml
  sed -i "/^\[fleet.roster\]/a $line" /etc/mapd/config.toml
  echo "made /etc/mapd/robot.key; add this line to [fleet.roster] on every robot of the fleet:"
  echo "  $line"
fi
if [ -n "$link_key" ] && ! [ "$link_key" -ef /etc/mapd/link.key ]; then
  # (the installed key itself, given again: install refuses to copy a file onto itself, and the
  # script stopped half-way through an upgrade)
  install -m 0640 -o root -g mapd "$link_key" /etc/mapd/link.key
elif [ -z "$link_key" ] && [ ! -f /etc/mapd/link.key ]; then
  /opt/mapd/venv/bin/mapd keygen --link-key /etc/mapd/link.key >/dev/null
  chgrp mapd /etc/mapd/link.key && chmod 0640 /etc/mapd/link.key
  echo "made the fleet's uwb link key /etc/mapd/link.key: copy it to every robot (install.sh --link-key FILE)"
fi
# Compile the lossless codec's numba kernels now, as the daemon's user, into the cache the unit names
# (NUMBA_CACHE_DIR): the first compile takes about 30 s, which a robot should not spend at start-up.
install -d -m 0750 -o mapd -g mapd /var/cache/mapd
runuser -u mapd -- env NUMBA_CACHE_DIR=/var/cache/mapd/numba MAPD_MODELS=/opt/mapd/models \
  /opt/mapd/venv/bin/mapd warmup --codec lossless zstd raw paper
# The unit is replaced on every run: local changes (ReadWritePaths= for an output folder elsewhere)
# go in a drop-in, which an upgrade keeps: systemctl edit mapd
install -m 0644 deploy/mapd.service /etc/systemd/system/mapd.service
# The udev rule only where there is none: the example must be edited to the robot's radio, and an
# upgrade wrote over the edited one
if [ ! -f /etc/udev/rules.d/99-mapd-uwb.rules ]; then
  install -m 0644 deploy/99-mapd-uwb.rules /etc/udev/rules.d/99-mapd-uwb.rules
  echo "installed /etc/udev/rules.d/99-mapd-uwb.rules: edit its match to this robot's radio (see its comments)"
fi
udevadm control --reload 2>/dev/null || true
udevadm trigger --subsystem-match=tty --action=change 2>/dev/null || true  # a radio plugged in already
systemctl daemon-reload
systemd-analyze verify /etc/systemd/system/mapd.service || true
# An upgrade: a running daemon goes on with the old code until it restarts (nothing if not running).
# Restarted only into a config the new code takes: one it refuses would stop the robot's mapd
# (exit 2, not restarted) until someone looks.
if systemctl is-active -q mapd 2>/dev/null; then
  # (as the unit runs it: its MAPD_MODELS too, which a config from before model_dir was set needs)
  if runuser -u mapd -- env MAPD_MODELS=/opt/mapd/models \
       /opt/mapd/venv/bin/mapd check-config /etc/mapd/config.toml >/dev/null; then
    systemctl try-restart mapd 2>/dev/null || true
  else
    echo "mapd check-config refuses /etc/mapd/config.toml (above): mapd not restarted; it goes on" \
         "with the old code until the config is fixed and it is restarted" >&2
  fi
fi
echo "installed. start with: systemctl enable --now mapd; check with: mapd status"
