"""MCAP recordings of the fleet (:mod:`~mapd.record.writer`) and ``mapd record info`` (:mod:`~mapd.record.info`)."""
