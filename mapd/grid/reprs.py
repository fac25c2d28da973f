"""An untrusted value shown in one short line, at a bounded cost, for the error that names it.

A map file's YAML or a config's TOML may hold anything, and the error that refuses a value shows
it. :func:`short_repr` keeps that one readable line whatever the value: nested containers a few
levels and items deep, huge integers by their size, and an object whose own ``__repr__`` fails by
its type's name: never a hang, a ValueError or a traceback.
"""

from __future__ import annotations

import reprlib


class _BoundedRepr(reprlib.Repr):
    """A ``repr`` whose cost is bounded whatever the value.

    A YAML alias bomb (anchors nested ten deep, ten aliases each) is a few hundred bytes that
    ``repr`` expands to 10**10 items, and a hex integer of 64 KiB has more digits than Python
    converts to decimal (ValueError). Both are shown cut short instead.
    """

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel = 3
        self.maxdict = self.maxlist = self.maxtuple = self.maxset = self.maxfrozenset = 6
        self.maxstring = self.maxother = 60
        self.maxlong = 40

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 128:  # decimal conversion of a huge int is slow, or refused past 4300 digits
            return f"<{'-' if x < 0 else ''}integer of {x.bit_length()} bits>"
        return super().repr_int(x, level)


_BOUNDED_REPR = _BoundedRepr()


def short_repr(value: object, limit: int = 60) -> str:
    """``repr`` of an untrusted value cut to about ``limit`` characters, at a bounded cost.

    Nested containers are shown a few levels and items deep, huge integers by their size, so a
    hostile YAML or TOML value (an alias bomb, a 64 KiB hex number) is one short line, never a hang
    or a ValueError.
    """
    try:
        shown = _BOUNDED_REPR.repr(value)
    except Exception:  # a hostile object's own __repr__; a name is still one clear line
        shown = f"<{type(value).__name__}>"
    return shown if len(shown) <= limit else shown[: limit - 3] + "..."
