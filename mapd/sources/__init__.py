"""Map-source plugins: where a robot's own occupancy grid comes from."""

from mapd.sources.base import MapSource, SourceContext, SourceOptions

__all__ = ["MapSource", "SourceContext", "SourceOptions"]
