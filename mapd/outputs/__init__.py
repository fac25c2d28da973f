"""Output plugins: where the global map goes each time it changes (``[output] use = [...]``).

* :mod:`~mapd.outputs.base`: the interface (:class:`~mapd.outputs.base.Output`) and what each
  update carries (:class:`~mapd.outputs.base.GlobalUpdate`);
* :mod:`~mapd.outputs.files`: map_server files (``<name>.yaml`` and the image it names,
  ``<name>-<n>.pgm``) and ``transforms.json`` in a folder of your choice, written atomically;
* :mod:`~mapd.outputs.zenoh`: the global map as a signed, lossless mapd envelope on
  ``mapd/<fleet>/<robot>/global``, with a queryable for late joiners.
"""
