"""mapd: share and fuse 2D occupancy-grid maps across a robot fleet over thin radio links."""

__version__ = "0.1.0"
