"""One module per CLI command group, each with ``register(subparsers)``; heavy imports stay inside handlers."""
