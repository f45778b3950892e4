"""Frame ranges, frame-numbered names and shard specs (usdfiber.farm.frames, shard_spec)."""
from __future__ import annotations

from pathlib import Path

import pytest

from usdfiber.farm.frames import FrameSpecError, MAX_FRAMES, frame_path, has_frame_token, parse_frames
from usdfiber.farm.shard_spec import Shard, ShardSpecError, parse_shard


@pytest.mark.parametrize("text, frames", [
    ("1001", [1001]),
    ("1001-1005", [1001, 1002, 1003, 1004, 1005]),
    ("1001-1010x3", [1001, 1004, 1007, 1010]),
    ("1001-1011x3", [1001, 1004, 1007, 1010]),          # the last frame is not forced in
    ("5,1-3,2", [1, 2, 3, 5]),                          # sorted, no repeats
    ("-2-1", [-2, -1, 0, 1]),
    (" 7 - 9 ", [7, 8, 9]),
])
def test_parse_frames(text, frames):
    assert parse_frames(text) == frames


@pytest.mark.parametrize("text, words", [
    ("", "empty frame range"),
    ("   ", "empty frame range"),
    ("1100-1001", "empty frame range"),
    ("1-10x0", "step must be >= 1"),
    ("1.5-3", "integer frames"),
    ("a-b", "integer frames"),
    ("1-2-3", "integer frames"),
    (f"1-{MAX_FRAMES + 1}", "more than"),
])
def test_bad_frame_ranges_are_one_line_errors(text, words):
    with pytest.raises(FrameSpecError) as e:
        parse_frames(text)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_frame_paths():
    assert frame_path("out/shot.####.exr", 1001) == Path("out/shot.1001.exr")
    assert frame_path("shot.####.exr", 7) == Path("shot.0007.exr")
    assert frame_path("shot.##.exr", 12345) == Path("shot.12345.exr")   # never truncated
    assert frame_path("shot.%04d.exr", 12) == Path("shot.0012.exr")
    assert frame_path("shot.%d.exr", 12) == Path("shot.12.exr")
    assert frame_path("shot.####.exr", -3) == Path("shot.-003.exr")
    assert has_frame_token("a/shot.####.exr") and not has_frame_token("a/shot.exr")
    for bad in ("shot.exr", "shot.##.#.exr", "dir.####/shot.####.exr"):
        with pytest.raises(FrameSpecError, match="one frame placeholder"):
            frame_path(bad, 1)


def test_shards_are_disjoint_and_cover_the_work():
    items = list(range(17))
    parts = [parse_shard(f"{i}/5").select(items) for i in range(1, 6)]
    assert sorted(sum(parts, [])) == items
    assert all(len(p) in (3, 4) for p in parts)
    assert parse_shard(" 2 / 3 ") == Shard(2, 3) and str(Shard(2, 3)) == "2/3"
    assert parse_shard("1/1").select(items) == items


@pytest.mark.parametrize("text, words", [
    ("0/3", "I must be between 1 and N=3"),
    ("4/3", "I must be between 1 and N=3"),
    ("1/0", "N must be between 1"),
    ("2", "expected I/N"),
    ("a/b", "expected I/N"),
    ("1.5/3", "expected I/N"),
])
def test_bad_shards_are_one_line_errors(text, words):
    with pytest.raises(ShardSpecError) as e:
        parse_shard(text)
    assert words in str(e.value) and "\n" not in str(e.value)


@pytest.mark.parametrize("spec, expected", [
    ("local:3", (3, "")), ("host:8786", (0, "tcp://host:8786")), ("tcp://10.0.0.1", (0, "tcp://10.0.0.1")),
    ("tcp://[::1]:8786", (0, "tcp://[::1]:8786")), ("tls://h:1", (0, "tls://h:1")), ("inproc://x", (0, "inproc://x")),
])
def test_scheduler_addresses(spec, expected):
    from usdfiber.farm.cluster import parse_scheduler

    assert parse_scheduler(spec) == expected


@pytest.mark.parametrize("spec, words", [
    ("", "expected an address"), ("a b", "expected an address"), ("bogus::x", "IPv6 address needs brackets"),
    ("tcp://h:abc", "a port in 1..65535"), ("tcp://h:0", "a port in 1..65535"), ("tcp://:8786", "a host"),
    ("foo://bar", "unknown protocol 'foo'"), ("local:0", "1 <= N <= 256"), ("local:x", "1 <= N <= 256"),
])
def test_bad_scheduler_addresses_are_one_line_errors_without_connecting(spec, words):
    from usdfiber.farm.cluster import FarmError, parse_scheduler

    with pytest.raises(FarmError) as e:
        parse_scheduler(spec)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_probes_outlive_their_bake_and_stale_ones_are_removed(tmp_path):
    """A task shared by two clients may be retried after one client finished: its probe must
    still be there. Probes older than PROBE_LIFETIME_S are removed by the next client."""
    import os

    from usdfiber.farm.cluster import PROBE_LIFETIME_S, verify_probe, write_probe

    old, fresh = write_probe(tmp_path), write_probe(tmp_path)
    past = os.stat(old.path).st_mtime - PROBE_LIFETIME_S - 10
    os.utime(old.path, (past, past))
    write_probe(tmp_path)
    assert not os.path.exists(old.path)
    verify_probe(fresh, tmp_path)  # still readable: raises FarmError otherwise
