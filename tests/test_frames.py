"""The one --frames grammar: parsing without data, how many frames must exist, resolution, tags."""

from __future__ import annotations

import pytest

from mono_map.errors import MonoMapError
from mono_map.frames import first_frames, frames_tag, parse_frames


@pytest.mark.parametrize("spec, n_total, frames, needed", [
    ("all", 7, list(range(7)), None),
    ("3", 7, [0, 1, 2], 3),                      # N = the first N frames, in every command
    ("2:5", 7, [2, 3, 4], 5),
    (":2", 7, [0, 1], 2),
    ("4:", 7, [4, 5, 6], None),
    ("0:7:3", 7, [0, 3, 6], 7),
    ("5,1", 7, [5, 1], 6),
    ("6,", 7, [6], 7),                           # one frame
])
def test_grammar(spec, n_total, frames, needed):
    sel = parse_frames(spec)
    assert sel.needed() == needed
    assert sel.resolve(n_total) == frames


@pytest.mark.parametrize("spec", ["a:b", "x", "5:2", "3:3", "-1:4", "0:4:0", "1:2:3:4", "1,,2", "2,2", "0", ",",
                                  "1.5", ""])
def test_bad_syntax_refused_without_data(spec):
    with pytest.raises(MonoMapError, match="^--frames: "):
        parse_frames(spec)


def test_outside_the_sequence():
    with pytest.raises(MonoMapError, match="needs 100000 frames, the sequence has 6"):
        parse_frames("0:100000").resolve(6)
    with pytest.raises(MonoMapError, match="frame 9 is outside"):
        parse_frames("1,9").resolve(6)
    with pytest.raises(MonoMapError, match="starts at frame 8"):
        parse_frames("8:").resolve(6)


def test_default_is_up_to():
    sel = parse_frames(None, default=first_frames(500))
    assert sel.needed() == 500 and sel.resolve(6) == list(range(6)) and sel.resolve(4541) == list(range(500))
    assert "first 500" in sel.text
    assert parse_frames(None).resolve(3) == [0, 1, 2]


def test_tags():
    assert frames_tag(range(0, 500)) == "f0-500"
    assert frames_tag([0, 10, 20]) == "f0-21s10"
    assert frames_tag([3, 1]).startswith("flist") and frames_tag([3, 1]) != frames_tag([1, 3])
