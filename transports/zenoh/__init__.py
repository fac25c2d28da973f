"""The ``zenoh`` transport: pub/sub over Wi-Fi with liveliness and a keyframe queryable.

* :mod:`~transports.zenoh.core` holds the rules, sans-I/O (what to publish, what to ack, when);
  :mod:`~transports.zenoh.answers` is its side facing peers' keyframe queries (heeded, rationed),
  :mod:`~transports.zenoh.core_types` what it gives back (steps, counters), and
  :mod:`~transports.zenoh.acks` the signed ack payload;
* :mod:`~transports.zenoh.link` is the asyncio adapter registered as the ``zenoh`` plugin;
  :mod:`~transports.zenoh.intake` and :mod:`~transports.zenoh.sending` are its receiving and
  sending halves (mixins over its state);
* :mod:`~transports.zenoh.keys` names the key expressions; :mod:`~transports.zenoh.session` builds
  the zenoh config; :mod:`~transports.zenoh.routers` follows the routers the session is connected
  to; :mod:`~transports.zenoh.jobs` runs every blocking zenoh call off the loop;
  :mod:`~transports.zenoh.handlers` lets close() wait for zenoh's callback threads;
  :mod:`~transports.zenoh.fleets` notes robots of other fleets on the same network;
  :mod:`~transports.zenoh.limits` keeps what each peer announced it takes.
"""
