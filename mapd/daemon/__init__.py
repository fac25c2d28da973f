"""The running daemon (``mapd run``): lifecycle, publisher, receiver, state store, status socket, systemd."""
