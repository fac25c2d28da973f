"""Training the paper codec's networks (``mapd train``).

* :mod:`~mapd.train.data` splits maps by place and cuts tiles with their surroundings;
* :mod:`~mapd.train.settings` holds what decides a run and refuses a bad setting before any work;
* :mod:`~mapd.train.loop` is the training loop and writes a model folder;
* :mod:`~mapd.train.card` measures whole maps through the codec and writes ``MODEL_CARD.md``.
* :mod:`~mapd.train.snapshots` replays logs and simulated runs into maps in the making (cached);
* :mod:`~mapd.train.heldout` scores models on a held-out log's growing maps and held-out finished maps.
"""
