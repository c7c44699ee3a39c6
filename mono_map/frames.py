"""The one ``--frames`` grammar, the same in every command (build, eval, predict, eval-depth, demo, synth).

    all          every frame of the sequence
    N            the first N frames (= 0:N)
    A:B[:S]      frames A, A+S, ... below B (A defaults to 0, B to the end, S to 1)
    I,J,...      exactly these frames (a single one: ``7,``)

A selection is parsed and checked before any data is opened: :func:`parse_frames` needs no
sequence, :meth:`FrameSelection.needed` says how many frames the sequence must hold (so a
synthetic sequence is rendered only that far, and only once the request is known to be valid),
and :meth:`FrameSelection.resolve` turns it into frame indices of a sequence of known length.
A command's default selection may be "up to" a count (``build``: the first 500 frames, fewer if
the sequence is shorter); a selection the user typed must lie inside the sequence.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

from mono_map.errors import MonoMapError

GRAMMAR = "'all', N (the first N frames), A:B[:S] or a comma list I,J,..."


@dataclass(frozen=True)
class FrameSelection:
    """A parsed ``--frames`` value (frame indices are 0-based, ``stop`` exclusive)."""

    text: str                              # as given, for messages
    start: int = 0
    stop: int | None = None                # None: to the end of the sequence
    step: int = 1
    indices: tuple[int, ...] | None = None  # an explicit list (then start/stop/step are unused)
    up_to: bool = False                    # a default: clip to a shorter sequence instead of refusing
    option: str = "--frames"

    def needed(self) -> int | None:
        """How many frames (from frame 0) the sequence must hold; None = all it has."""
        if self.indices is not None:
            return max(self.indices) + 1
        return self.stop

    def resolve(self, n_total: int) -> list[int]:
        """The frame indices inside a sequence of ``n_total`` frames; MonoMapError if outside it."""
        if self.indices is not None:
            bad = [i for i in self.indices if i >= n_total]
            if bad:
                raise MonoMapError(f"{self.option}: frame {bad[0]} is outside the sequence's {n_total} frames "
                                   f"(0..{n_total - 1})")
            return list(self.indices)
        stop = n_total if self.stop is None else self.stop
        if self.up_to:
            stop = min(stop, n_total)
        if stop > n_total:
            raise MonoMapError(f"{self.option}: {self.text!r} needs {stop} frames, the sequence has {n_total}")
        if self.start >= stop:
            raise MonoMapError(f"{self.option}: {self.text!r} starts at frame {self.start}, "
                               f"the sequence has {n_total} frames")
        return list(range(self.start, stop, self.step))

    def describe(self, frames: list[int]) -> str:
        """Human description of the resolved ``frames``."""
        what = describe_indices(frames)
        if self.up_to:
            return f"{what} (default; --frames all for the whole sequence)"
        return what


def parse_frames(spec: str | None, default: FrameSelection | None = None, option: str = "--frames") -> FrameSelection:
    """Parse ``spec`` (see the module docstring); None → ``default`` (None: all frames)."""
    if spec is None:
        return default if default is not None else FrameSelection("all", option=option)
    s = str(spec).strip()

    def bad(why: str) -> MonoMapError:
        return MonoMapError(f"{option}: {spec!r} {why} (expected {GRAMMAR})")

    def integer(x: str, what: str) -> int:
        try:
            v = int(x)
        except ValueError:
            raise bad(f"has a {what} that is not an integer") from None
        if v < 0:
            raise bad(f"has a negative {what}")
        return v

    if s == "all":
        return FrameSelection(s, option=option)
    if "," in s:
        items = [x.strip() for x in s.split(",")]
        if items[-1] == "":
            items = items[:-1]
        if not items or any(x == "" for x in items):
            raise bad("has an empty item")
        idx = tuple(integer(x, "frame") for x in items)
        if len(set(idx)) != len(idx):
            raise bad("lists a frame twice")
        return FrameSelection(s, indices=idx, option=option)
    if ":" in s:
        parts = s.split(":")
        if len(parts) > 3:
            raise bad("has more than two ':'")
        start = integer(parts[0], "start") if parts[0].strip() else 0
        stop = integer(parts[1], "stop") if parts[1].strip() else None
        step = integer(parts[2], "step") if len(parts) == 3 and parts[2].strip() else 1
        if step < 1:
            raise bad("has a step below 1")
        if stop is not None and stop <= start:
            raise bad("selects no frames (stop <= start)")
        return FrameSelection(s, start=start, stop=stop, step=step, option=option)
    n = integer(s, "frame count")
    if n < 1:
        raise bad("selects no frames")
    return FrameSelection(s, stop=n, option=option)


def first_frames(n: int) -> FrameSelection:
    """A command's default: the first ``n`` frames, or all of a shorter sequence."""
    return FrameSelection(f"the first {n} frames", stop=int(n), up_to=True)


def _as_range(frames: list[int]) -> range | None:
    if not frames:
        return None
    step = frames[1] - frames[0] if len(frames) > 1 else 1
    r = range(frames[0], frames[-1] + 1, step) if step > 0 else None
    return r if r is not None and list(r) == list(frames) else None


def describe_indices(frames: list[int]) -> str:
    r = _as_range(frames)
    if r is None:
        return f"{len(frames)} listed frames"
    if r.step == 1:
        return f"frames {r.start}:{r.stop}"
    return f"frames {r.start}:{r.stop}:{r.step} ({len(r)} frames)"


def frames_tag(frames) -> str:
    """A short file-name tag for resolved frames: ``f0-500``, ``f0-500s10``, else a digest of the list."""
    frames = list(frames)
    r = _as_range(frames)
    if r is not None and r.step == 1:
        return f"f{r.start}-{r.stop}"
    if r is not None:
        return f"f{r.start}-{r.stop}s{r.step}"
    return "flist" + hashlib.sha256(",".join(map(str, frames)).encode()).hexdigest()[:8]
