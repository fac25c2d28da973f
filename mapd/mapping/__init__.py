"""Making maps: the log-odds mapper, log readers, lidar and simulated worlds and robots, a scan matcher.

* :mod:`~mapd.mapping.mapper` integrates scans into an occupancy grid (every map source uses it);
* :mod:`~mapd.mapping.replay` runs a CARMEN log through it, as one robot of several sharing the log;
* :mod:`~mapd.mapping.carmen` reads CARMEN logs; :mod:`~mapd.mapping.lidar` casts simulated scans;
* :mod:`~mapd.mapping.worldgen` draws buildings; :mod:`~mapd.mapping.simrobot` drives robots in them;
* :mod:`~mapd.mapping.localize` matches a scan against a map (Figure 9 of ``mapd bench paper``).
"""
