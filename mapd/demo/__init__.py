"""``mapd demo``: a fleet of real daemons on one machine, and the report it leaves.

* :mod:`~mapd.demo.fleet` starts the daemons, waits for the maps to converge and stops them;
* :mod:`~mapd.demo.report` draws the pictures and prints the summary table.
"""
