"""bench.real_splits: a split's map from two ranges of the real walk (two drives of one map)."""


def test_middle_third_map_holds_both_ranges_from_their_first_scans(shared_data, tmp_path):
    from bench.real import walk_config_handheld
    from bench.real_splits import SPLITS, build_split_map
    from tests.tracking.walk import WALK_DIR, open_walk

    cfg = walk_config_handheld()
    seq = open_walk(shared_data / WALK_DIR, cfg)
    ranges, held = SPLITS["middle third"]
    store = build_split_map(seq, tmp_path / "m", cfg, ranges)
    drives = store.params["drives"]
    assert [d["keyframes"] for d in drives] == [b - a for a, b in ranges]  # every map scan a keyframe
    # the drives start at the ranges' first scans: nothing of the held-out stretch 59-117 is in the map
    stamps = [f.stamp for f in seq.frames(0, 177)]
    assert [d["first_stamp"] for d in drives] == [stamps[a] for a, _ in ranges]
    assert len(store.entries) >= 2
