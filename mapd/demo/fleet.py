"""``mapd demo``: a small fleet on one machine, every robot a real ``mapd run`` process.

Each robot gets its own config, state and runtime directory under ``<out>/run``. Over UWB, the
robots' serial ports are socat pty pairs joined by the emulated radio in :mod:`transports.uwb.relay`
(12.5 kb/s, shared by everyone on the channel); over zenoh, each daemon listens on a loopback port
and connects to the others with multicast scouting off. The demo polls every daemon's control
socket for live progress, stops them with SIGTERM, and writes the figures and a metrics table.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from mapd.daemon.status_socket import query
from mapd.daemon.versions import label
from mapd.demo.ports import free_port, free_ports
from mapd.errors import DaemonError, MapdError

UWB_RATE = 12500
#: The base station's name with ``--ros2-listen``.
BASE = "base"


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def write_config(path: Path, tables: dict[str, dict[str, Any]]) -> None:
    """Write tables (``{"source.sim": {...}}``, or nested dicts as in ``tomllib``'s output) as TOML."""
    lines: list[str] = []

    def table(name: str, values: dict[str, Any]) -> None:
        lines.append(f"[{name}]")
        lines.extend(f"{k} = {_toml_value(v)}" for k, v in values.items() if not isinstance(v, dict))
        lines.append("")
        for k, v in values.items():
            if isinstance(v, dict):
                table(f"{name}.{k}", v)

    for name, values in tables.items():
        table(name, values)
    path.write_text("\n".join(lines))


class Fleet:
    """Starts, watches and stops the demo's daemons and links."""

    def __init__(self, args: argparse.Namespace, *, sim_options: dict[str, Any] | None = None) -> None:
        """``args`` as ``mapd demo`` parses them; ``sim_options`` add or override ``[source.sim]`` keys."""
        self.args = args
        self.sim_options = sim_options or {}
        self.n = args.robots
        self.names = [f"robot{i}" for i in range(self.n)]
        #: ``--ros2-listen``: a base station (source ``none``) whose ros2 output listens there.
        self.base = BASE if getattr(args, "ros2_listen", None) else None
        self.run_dir = args.out / "run"
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.relay: subprocess.Popen[str] | None = None
        self.router: subprocess.Popen[str] | None = None
        self.ports: dict[str, str] = {}

    # ------------------------------------------------------------------ setup
    def prepare(self) -> None:
        if self.run_dir.exists():
            shutil.rmtree(self.run_dir)
        self.run_dir.mkdir(parents=True)
        if self.args.transport == "uwb":
            self._start_relay()
        router = self._start_router() if getattr(self.args, "router", False) else None
        zenoh_ports = free_ports(len(self.members))
        poses = self._start_poses()
        key_files, roster, link_key = self._make_keys()
        for i, name in enumerate(self.members):
            d = self.run_dir / name
            (d / "state").mkdir(parents=True)
            tables: dict[str, dict[str, Any]] = {
                "robot": {"name": name, "fleet": "demo", "key_file": str(key_files[name])},
                "fleet": {"link_key_file": str(link_key), "roster": roster},
                "state": {"dir": str((d / "state").resolve()), "runtime_dir": str((d / "run").resolve())},
                "log": {"level": "info"},
            }
            tables.update(self._source_tables(i) if name != self.base else self._base_tables())
            tables["codec"] = {"use": self.args.codec, "keyframe_every": 10, "measure_quality": True}
            if self.args.transport == "uwb":
                tables["transports"] = {"use": ["uwb"]}
                tables["transports.uwb"] = {
                    "port": self.ports[name],
                    "link_rate_bps": UWB_RATE,
                    "mac": "tdma" if len(self.members) > 2 else "none",
                }
                tables["transports.uwb.nodes"] = {r: j + 1 for j, r in enumerate(self.members)}
            elif router is not None:  # every robot a client of one router, as in a building
                tables["transports"] = {"use": ["zenoh"]}
                tables["transports.zenoh"] = {
                    "mode": "client",
                    "connect": [router],
                    "multicast_scouting": False,
                }
            else:
                tables["transports"] = {"use": ["zenoh"]}
                tables["transports.zenoh"] = {
                    "mode": "peer",
                    "listen": [f"tcp/127.0.0.1:{zenoh_ports[i]}"],
                    "connect": [f"tcp/127.0.0.1:{p}" for j, p in enumerate(zenoh_ports) if j != i],
                    "multicast_scouting": False,
                }
            tables["fusion"] = {"mode": "logodds", "debounce_s": 1.0}
            record = getattr(self.args, "record", None)
            if record is not None and i == 0:
                tables["record"] = {"path": str(Path(record).resolve())}
            tables["fusion.poses"] = {r: list(p) for r, p in poses.items()} if poses else {}
            view = getattr(self.args, "view", None)
            if view is not None and i == 0:  # robot0's live view, on loopback (no token needed)
                tables["view"] = {"listen": f"127.0.0.1:{view}"}
            write_config(d / "config.toml", tables)

    def _make_keys(self) -> tuple[dict[str, Path], dict[str, str], Path]:
        """Every robot's own signing key, the roster that lists them, and the uwb link key.

        The demo fleet is signed as a real one is (``mapd keygen`` does the same on a robot).
        """
        import secrets

        from mapd.files import write_new_secret
        from mapd.identity import Identity

        keys = self.run_dir / "keys"
        keys.mkdir(mode=0o700)
        files: dict[str, Path] = {}
        roster: dict[str, str] = {}
        for name in self.members:
            identity = Identity.generate(name)
            files[name] = (keys / f"{name}.key").resolve()
            identity.write(files[name])
            roster[name] = identity.public_text
        link = (keys / "link.key").resolve()
        write_new_secret(link, secrets.token_hex(32).encode() + b"\n")  # as mapd keygen --link-key
        return files, roster, link

    def _start_router(self) -> str:
        """A zenoh router process (deploy/zenoh/router.json5, on a loopback port); returns its endpoint."""
        from mapd.data import REPO_ROOT

        endpoint = f"tcp/127.0.0.1:{free_port()}"
        cmd = [sys.executable, "-m", "transports.zenoh.router", "--listen", endpoint]
        example = REPO_ROOT / "deploy" / "zenoh" / "router.json5"
        if example.exists():
            cmd += ["--config", str(example)]
        self.router = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert self.router.stdout is not None
        line = self.router.stdout.readline()
        if not line.startswith("listening"):
            raise DaemonError(f"the zenoh router did not start: {line.strip() or 'no output'}")
        return endpoint

    def _start_relay(self) -> None:
        """The emulated radio: a separate process joining every robot's socat pty at 12.5 kb/s."""
        uwb = self.run_dir / "uwb"
        uwb.mkdir()
        cmd = [
            sys.executable,
            "-m",
            "transports.uwb.relay",
            "--robots",
            str(len(self.members)),
            "--rate-bps",
            str(UWB_RATE),
            "--seed",
            str(self.args.seed),
            "--dir",
            str(uwb),
            "--drop",
            str(getattr(self.args, "drop", 0.0)),
            "--flip",
            str(getattr(self.args, "flip", 0.0)),
        ]
        for outage in getattr(self.args, "outage", []):
            cmd += ["--outage", outage]
        for pair in getattr(self.args, "out_of_range", []):
            cmd += ["--out-of-range", pair]
        if getattr(self.args, "collisions", False):
            cmd.append("--collisions")  # frames that overlap in the air garble each other
        self.relay = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert self.relay.stdout is not None
        deadline = time.monotonic() + 15
        while len(self.ports) < len(self.members):
            line = self.relay.stdout.readline()
            if not line or time.monotonic() > deadline:
                raise DaemonError(f"the UWB relay did not start: {line.strip() or 'no output'}")
            if line.startswith("robot "):
                idx, port = line[len("robot ") :].split(":", 1)
                self.ports[self.members[int(idx)]] = port.strip()

    def _source_tables(self, i: int) -> dict[str, dict[str, Any]]:
        if self.args.log is not None:
            return {
                "source": {"use": "laserlog"},
                "source.laserlog": {
                    "log": str(Path(self.args.log).resolve()),
                    "robots": self.n,
                    "index": i,
                    "every": 20,
                    # The intel log spans 45 minutes; replay each robot's part within the demo.
                    "realtime": max(2700.0 / self.args.duration, 1.0),
                },
            }
        return {
            "source": {"use": "sim"},
            "source.sim": {
                "seed": self.args.seed,
                "robots": self.n,
                "index": i,
                "emit_period": 5.0,
                "realtime": 4.0,
                "beams": 180,
                "scan_rate": 2.0,
                **self.sim_options,
            },
        }

    @property
    def members(self) -> list[str]:
        """Every daemon to run: the robots (``names``, which a test may cut down after ``prepare``),
        then the base station if any."""
        return self.names + ([self.base] if self.base else [])

    def _base_tables(self) -> dict[str, dict[str, Any]]:
        """The base station's: no map of its own, and the fused map and each robot's on ROS 2
        (rmw_zenoh) at the endpoint."""
        return {
            "source": {"use": "none"},
            "output": {"use": ["ros2"]},
            "output.ros2": {
                "listen": [self.args.ros2_listen],
                "connect": [],
                "frame": "map",
                "robot_map_topic": "/{robot}/map",
            },
        }

    def _start_poses(self) -> dict[str, tuple[float, float, float]]:
        """Known start poses for known-pose fusion, from the deterministic source itself."""
        from mapd import config, plugins
        from mapd.sources.base import SourceContext

        poses = {}
        for i, name in enumerate(self.names):
            tables = self._source_tables(i)
            use = tables["source"]["use"]
            cls = plugins.load("source", use)
            opts = config.validate(cls.Options, tables[f"source.{use}"], "demo")
            pose = cls(opts, SourceContext(robot=name)).start_pose()
            if pose is None:
                return {}
            poses[name] = (round(pose.x, 6), round(pose.y, 6), round(pose.yaw, 6))
        return poses

    def start(self, only: list[str] | None = None) -> None:
        """Start every robot's daemon (or only those named, e.g. to start the others later)."""
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        for name in self.members if only is None else only:
            d = self.run_dir / name
            log = open(d / "daemon.log", "wb")  # noqa: SIM115 - lives as long as the process
            self.procs[name] = subprocess.Popen(
                [sys.executable, "-m", "mapd", "run", "--config", str(d / "config.toml")],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=env,
            )

    def status(self) -> dict[str, dict[str, Any]]:
        out = {}
        for name in self.members:
            sock = self.run_dir / name / "run" / "mapd.sock"
            try:
                out[name] = query(sock, timeout=2.0)
            except DaemonError:
                continue
        return out

    def check_alive(self) -> None:
        for name, p in self.procs.items():
            if p.poll() is not None:
                tail = (
                    (self.run_dir / name / "daemon.log").read_text(errors="replace").strip().splitlines()[-5:]
                )
                if p.returncode < 0:  # a signal, not an exit: its log's last lines are not why
                    try:
                        sig = f" ({signal.Signals(-p.returncode).name})"
                    except ValueError:  # a real-time signal has no name of its own
                        sig = ""
                    how = f"was killed by signal {-p.returncode}{sig}"
                    raise DaemonError(f"{name} {how}; stopping the other robots")
                raise DaemonError(f"{name} exited with code {p.returncode}: " + " | ".join(tail))

    def stop(self, timeout: float = 10.0) -> dict[str, int | None]:
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes: dict[str, int | None] = {}
        deadline = time.monotonic() + timeout
        for name, p in self.procs.items():
            try:
                codes[name] = p.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                # Where it hangs, in its log (every thread's stack), before it is killed.
                p.send_signal(signal.SIGUSR1)
                time.sleep(1.0)
                p.kill()
                codes[name] = None
                log = self.run_dir / name / "daemon.log"
                tail = log.read_text(errors="replace").splitlines()[-60:]
                print(
                    f"{name} did not stop within {timeout:g} s; the end of {log}:",
                    *tail,
                    sep="\n",
                    file=sys.stderr,
                )
        if self.router is not None and self.router.poll() is None:
            self.router.send_signal(signal.SIGTERM)
            try:
                self.router.wait(5)
            except subprocess.TimeoutExpired:
                self.router.kill()
        if self.relay is not None and self.relay.poll() is None:
            self.relay.send_signal(signal.SIGTERM)
            try:
                out, _ = self.relay.communicate(timeout=5)
                (self.run_dir / "uwb" / "relay-stats.json").write_text(
                    out[out.find("{") :] if "{" in out else out
                )
            except subprocess.TimeoutExpired:
                self.relay.kill()
        return codes


def _progress_line(t: float, snaps: dict[str, dict[str, Any]]) -> str:
    parts = [f"t={t:5.1f}s"]
    for name, s in snaps.items():
        link: dict[str, Any] = next(iter(s.get("links", {}).values()), {})
        rate = link.get("rate_bps") or UWB_RATE
        tx = link.get("tx_bps", link.get("goodput_bps"))
        use = f"{100 * tx / rate:3.0f}%" if isinstance(tx, int | float) else "  -"
        conf: list[float] = [
            t["confidence"]
            for t in (s.get("fusion", {}).get("robots") or {}).values()
            if isinstance(t, dict) and t.get("confidence") is not None
        ]
        peers = ",".join(f"{p}:{label(v.get('version'))}" for p, v in s.get("peers", {}).items()) or "-"
        c = s.get("codec", {})
        parts.append(
            f"{name} {label(s.get('source', {}).get('version', 0))} sent {c.get('keyframes', 0)}k+{c.get('deltas', 0)}d "
            f"link {use} has[{peers}] conf {min(conf) if conf else float('nan'):.2f}"
        )
    return " | ".join(parts)


def run_demo(args: argparse.Namespace) -> int:
    """Run the demo end to end; returns the exit code."""
    from mapd.demo.report import write_report

    if args.robots < 2:
        raise MapdError("the demo needs at least 2 robots")
    if args.transport == "uwb" and shutil.which("socat") is None:
        raise MapdError("the UWB demo needs socat: sudo apt-get install -y socat")
    for pair in getattr(args, "out_of_range", []):
        if args.transport != "uwb":
            raise MapdError("--out-of-range is a fault of the emulated UWB radio: add --transport uwb")
        if any(int(i) >= args.robots for i in pair.split("-")):
            raise MapdError(f"--out-of-range {pair}: robots are numbered 0..{args.robots - 1}")
    fleet = Fleet(args)
    print(
        f"mapd demo: {args.robots} robots, {args.transport} link, codec {args.codec}, "
        f"{'log ' + str(args.log) if args.log else 'simulated building seed ' + str(args.seed)}, "
        f"{args.duration:.0f} s",
        flush=True,
    )
    # Each robot would compile the codec's numba kernels at start (about 30 s the first time) inside
    # the demo's window, and one stopped mid-compile outlasts its stop timeout: compile once here,
    # into the on-disk cache every robot then reads.
    from mapd.codec.api import warm_up

    took = warm_up(args.codec)
    if took > 2.0:
        print(f"codec {args.codec} ready in {took:.0f} s (compiled once, cached for the robots)", flush=True)
    try:
        fleet.prepare()
        fleet.start()
    except BaseException:  # a bad --log, say: the radio relay and its socat ptys must not outlive it
        fleet.stop()
        raise
    if fleet.base is not None:
        print(
            f"ROS 2 (rmw_zenoh): the base station publishes /map, each robot's /<robot>/map, /tf_static "
            f"and /tf on {args.ros2_listen}; "
            f"see README 'With ROS 2'",
            flush=True,
        )
    if getattr(args, "view", None) is not None:
        print(f"live view of robot0: http://127.0.0.1:{args.view}/", flush=True)
    t0 = time.monotonic()
    snaps: dict[str, dict[str, Any]] = {}
    try:
        while (t := time.monotonic() - t0) < args.duration:
            time.sleep(2.0)
            fleet.check_alive()
            snaps = fleet.status() or snaps
            if snaps:
                print(_progress_line(t, snaps), flush=True)
    except KeyboardInterrupt:
        print("interrupted; stopping robots", flush=True)
    finally:
        codes = fleet.stop()
    bad = {n: c for n, c in codes.items() if c != 0}
    if bad:
        print(f"warning: daemons exited with {bad}", file=sys.stderr)
    summary = write_report(args.out, fleet.run_dir, fleet.names, snaps, args)
    print(summary)
    return 0 if not bad else 1
