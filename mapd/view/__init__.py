"""The live web view of the fleet, served by the daemon itself (``[view] listen``), read-only.

* :mod:`~mapd.view.tiles`: the global map as PNG tiles and which tiles changed (pure numpy)
* :mod:`~mapd.view.queue`: one viewer's bounded, latest-wins queue of server-sent events (sans-I/O)
* :mod:`~mapd.view.model`: the view's state and messages: tiles, robots, status (sans-I/O)
* :mod:`~mapd.view.server`: the aiohttp adapter: routes, token, SSE, viewer cap
* :mod:`~mapd.view.connections`: its sockets below HTTP: counted from accept, capped, fitted to the
  open-file limit; bad requests and clients gone counted, not logged
* :mod:`~mapd.view.live`: the view as a daemon output (CPU work on the output thread)
* ``static/``: the page (plain HTML, CSS and a little JavaScript; no CDN)
"""
