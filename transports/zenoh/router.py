"""A zenoh router in a process of its own: ``python -m transports.zenoh.router [--config F] [--listen EP]``.

For benches, tests and small fleets without ``zenohd`` (the eclipse-zenoh binding runs a router
as well). It opens a session in router mode from ``--config`` (a zenoh JSON5 file, such as
``deploy/zenoh/router.json5``) with ``--listen`` endpoints set over it, prints one line
``listening on <endpoints>`` when ready, and runs until SIGTERM or SIGINT.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading


def main(argv: list[str] | None = None) -> int:
    import zenoh

    ap = argparse.ArgumentParser(prog="python -m transports.zenoh.router")
    ap.add_argument("--config", default=None, help="zenoh JSON5 config (default: an empty one)")
    ap.add_argument("--listen", action="append", default=[], help="endpoint to listen on (repeatable)")
    args = ap.parse_args(argv)
    try:
        conf = zenoh.Config.from_file(args.config) if args.config else zenoh.Config()
        conf.insert_json5("mode", '"router"')
        if args.listen:
            conf.insert_json5("listen/endpoints", json.dumps(args.listen))
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"router: cannot start: {exc}", file=sys.stderr, flush=True)
        return 1
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    print(f"listening on {', '.join(args.listen) or 'the config file endpoints'}", flush=True)
    stop.wait()
    session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
