"""Swarm benchmark: N robots share maps over one simulated UWB channel, in virtual time.

A discrete-event simulation runs the real sans-I/O UWB cores (:class:`~transports.uwb.arq.ArqEndpoint`
with its pacing, TDMA or backoff medium access and frame signing) and the daemon's real publisher
core, on real map streams coded by the real codecs (robots drive the simulator's building, ``--sim``,
or replay slices of a CARMEN log, ``--log``), over a broadcast radio: a bit rate, collisions, frame
loss, and range with a loss per wall crossed. It reports, per fleet size, codec and MAC, how stale
each robot's copy of each other robot's map gets (p50, p95, max, and in periods), how long the fleet
takes to converge after the last change, channel use, the acks' share of it, bytes per robot, and
frames lost to collisions and to loss.

Modules: ``streams`` (versions and paths, cached; payload sizes by the real codecs), ``radio`` (the
medium), ``links`` (range and walls), ``des`` (the event loop), ``node`` (one robot: ARQ + publisher),
``policy`` (hooks for relay and for who acks), ``sim`` (one run), ``metrics``, ``bound`` (``--bound``:
what one scheduler that knows everything would do on the same channel), ``args`` (the command's
options), ``run`` (the command).
"""

from mapd.bench.swarm.args import add_arguments
from mapd.bench.swarm.run import COLUMNS, run

HELP = "N robots on one simulated UWB channel (real ARQ, MAC, codecs): staleness, convergence, channel use"

__all__ = ["COLUMNS", "HELP", "add_arguments", "run"]
