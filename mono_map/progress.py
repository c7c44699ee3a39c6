"""Progress bars for long loops: items/s and ETA on stderr.

Bars still open when a command fails are closed by :func:`close_bars` (the CLI calls it before
printing the error), so the error line starts on a line of its own, not after the bar.
"""

from __future__ import annotations

import os
import sys
import weakref
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm

T = TypeVar("T")

_OPEN: "weakref.WeakSet[tqdm]" = weakref.WeakSet()


def progress(items: Iterable[T], total: int | None = None, desc: str = "", unit: str = "frame") -> Iterator[T]:
    """Wrap ``items`` in a progress bar showing rate (``unit``/s) and ETA.

    ``MONO_MAP_PROGRESS=0`` disables it; when stderr is not a terminal it redraws at most once a second.
    """
    disable = os.environ.get("MONO_MAP_PROGRESS", "1") == "0"
    bar = tqdm(items, total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True,
               mininterval=1.0 if not sys.stderr.isatty() else 0.1, disable=disable)
    _OPEN.add(bar)
    return _iterate(bar)


def _iterate(bar: tqdm) -> Iterator[T]:
    try:
        yield from bar
    finally:
        bar.close()
        _OPEN.discard(bar)


def close_bars() -> None:
    """Close every open bar (each ends its line), e.g. before an error message is printed."""
    for bar in list(_OPEN):
        bar.close()
        _OPEN.discard(bar)
