"""Training the paper codec's networks (``mapd train``).

* :mod:`~mapd.train.data` splits maps by place and cuts tiles with their surroundings;
* :mod:`~mapd.train.loop` is the training loop and writes a model folder;
* :mod:`~mapd.train.card` measures whole maps through the codec and writes ``MODEL_CARD.md``.
"""
