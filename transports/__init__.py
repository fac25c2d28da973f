"""First-party transport plugins. :mod:`transports.base` is the interface every transport implements."""
