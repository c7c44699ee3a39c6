"""Progress bars for long loops: items/s and ETA on stderr."""

from __future__ import annotations

import sys
from typing import Iterable, Iterator, TypeVar

from tqdm import tqdm

T = TypeVar("T")


def progress(items: Iterable[T], total: int | None = None, desc: str = "", unit: str = "frame") -> Iterator[T]:
    """Wrap ``items`` in a progress bar showing rate (``unit``/s) and ETA.

    Disabled by ``MONO_MAP_PROGRESS=0``; when stderr is not a terminal it redraws at most once a second.
    """
    import os

    disable = os.environ.get("MONO_MAP_PROGRESS", "1") == "0"
    return iter(
        tqdm(items, total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True,
             mininterval=1.0 if not sys.stderr.isatty() else 0.1, disable=disable)
    )
