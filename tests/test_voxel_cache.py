"""The voxel cache of an opened map, sized by memory (Map.open cache_bytes / cache_size, localize --cache-mb)."""

from __future__ import annotations

import numpy as np
import pytest

from favormap.errors import InputError


def test_a_map_that_fits_the_default_cache_is_read_once(small_map, small_sequence):
    """By default the cache holds the whole map where its grids fit DEFAULT_CACHE_BYTES: a second query
    reads nothing from disk; a cache of a few kB holds a few grids and reads again."""
    from favormap.localize import LocalizeConfig, Localizer
    from favormap.mapfile import Map
    from favormap.mapfile.reader import DEFAULT_CACHE_BYTES

    _, path = small_map
    with Map.open(path) as m:
        per_grid = m.grid_resolution**3 * (m.channels + 1) * 4
        assert m.cache_size == len(m) and m.cache_bytes == len(m) * per_grid <= DEFAULT_CACHE_BYTES
        assert m.info()["voxel_memory_bytes"] == m.cache_bytes
        loc = Localizer(m, LocalizeConfig(iterations=1, global_fallback=False))
        fr = small_sequence.frames[4]
        loc.localize(fr.image_path, fr.cam_from_world)
        first = m.bytes_read
        loc.localize(fr.image_path, fr.cam_from_world)
        assert first > 0 and m.bytes_read == first
    with Map.open(path, cache_bytes=10 * per_grid + 1) as small:
        assert small.cache_size == 10
        rows = np.arange(40)
        d1, _ = small.voxels(rows)
        before = small.bytes_read
        d2, _ = small.voxels(rows)
        assert small.bytes_read > before  # 40 grids do not fit 10
        np.testing.assert_array_equal(d1, d2)


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(cache_size=10, cache_bytes=1 << 20), "not both"),
        (dict(cache_bytes=0), "cache_bytes must be an integer >= 1"),
        (dict(cache_size=-3), "cache_size must be an integer >= 1"),
        (dict(cache_bytes=1.5), "cache_bytes must be an integer >= 1"),
    ],
)
def test_bad_cache_sizes_are_refused(small_map, kw, match):
    from favormap.mapfile import Map

    with pytest.raises(InputError, match=match):
        Map.open(small_map[1], **kw)


def test_localize_takes_the_cache_in_megabytes(small_map, small_sequence, capsys):
    from favormap.cli import main

    fr = small_sequence.frames[0]
    assert main(["localize", str(small_map[1]), str(fr.image_path), "--cache-mb", "0"]) != 0
    assert "--cache-mb must be at least 1" in capsys.readouterr().err


def test_the_build_summary_states_a_warm_localizers_voxel_memory(small_map, capsys):
    """The build summary gives the memory every grid of the map takes in a warm localizer, as favormap info does."""
    from favormap.cli.build_summary import print_summary, summary
    from favormap.mapfile import Map

    m, path = small_map
    s = summary(m, path)
    with Map.open(path) as opened:
        assert s["voxel_memory_bytes"] == opened.info()["voxel_memory_bytes"] == len(opened) * opened.grid_bytes > 0
    print_summary(s)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("voxel memory"))
    assert "a warm localizer holds them all" in line
