"""Event files whose timeidx follows either frame-time convention, with events exactly on frame times."""
import h5py
import numpy as np
import pytest

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset, convention_lines, main
from dagr_lite.data.errors import DatasetFormatError
from dagr_lite.data.events import EventFile, MAX_CONVENTION_PROBES, probe_frames
from dagr_lite.data.writer import write_events
from tests.conftest import HEIGHT, WIDTH, make_dataset
from tests.settings import sample_set

NUM_FRAMES = 30  # frames 2, 5, ..., 29 differ between the conventions: the last frame is one of them


def reference_time(k: int, convention: str) -> int:
    """Frame times spelled out as the two conventions define them, independently of the package."""
    return int(1e6 * ((1 / 30) * k)) if convention == "truncate" else round(1e6 * k / 30)


def on_frame_events(convention: str, num_frames: int = NUM_FRAMES, seed: int = 0) -> dict[str, np.ndarray]:
    """Events at every frame time of ``convention`` (the last frame's included), 1 us on either side, and at random."""
    rng = np.random.default_rng([seed])
    times = np.array([reference_time(k, convention) for k in range(num_frames)])
    on_frames = np.concatenate([times, times, times - 1, times + 1])
    elsewhere = rng.integers(0, times[-1] + 40_000, 500)
    t = np.sort(np.concatenate([on_frames[on_frames >= 0], elsewhere[~np.isin(elsewhere, on_frames)]]))
    return {"x": rng.integers(0, WIDTH, len(t)), "y": rng.integers(0, HEIGHT, len(t)), "t": t,
            "p": rng.integers(0, 2, len(t))}


def reference_timeidx(t: np.ndarray, num_frames: int, convention: str) -> np.ndarray:
    return np.array([int(np.searchsorted(t, reference_time(k, convention), side="left"))
                     for k in range(num_frames)])


def write_by_hand(path, events, num_frames: int, timeidx) -> None:
    """An event file in the release layout, written with h5py directly (as another tool would)."""
    with h5py.File(path, "w") as h5:
        h5[fmt.KEY_X], h5[fmt.KEY_Y] = events["x"].astype(np.uint16), events["y"].astype(np.uint16)
        h5[fmt.KEY_T], h5[fmt.KEY_P] = events["t"].astype(np.int64), events["p"].astype(np.uint8)
        h5[fmt.KEY_TIMEIDX] = np.asarray(timeidx, dtype=np.int64)


def write_in_convention(path, events, convention: str, num_frames: int = NUM_FRAMES) -> None:
    """``round`` through the package's writer, ``truncate`` by hand."""
    if convention == "round":
        write_events(path, **events, num_frames=num_frames, overwrite=True)
    else:
        write_by_hand(path, events, num_frames, reference_timeidx(events["t"], num_frames, "truncate"))


@pytest.mark.parametrize("convention", fmt.FRAME_TIME_CONVENTIONS)
def test_event_file_detects_the_convention_and_windows_follow_it(tmp_path, convention):
    events = on_frame_events(convention)
    path = tmp_path / "v.h5"
    write_in_convention(path, events, convention)
    reader = EventFile(path, num_frames=NUM_FRAMES)
    assert reader.convention == convention
    times = [reference_time(k, convention) for k in range(NUM_FRAMES)]
    assert [reader.frame_time_us(k) for k in range(NUM_FRAMES)] == times
    np.testing.assert_array_equal(reader.timeidx, reference_timeidx(events["t"], NUM_FRAMES, convention))
    t = events["t"]
    for k in range(NUM_FRAMES):
        t_next = times[k + 1] if k + 1 < NUM_FRAMES else times[k] + 33_334
        window = reader.window(times[k], t_next)
        np.testing.assert_array_equal(window["t"], t[(t >= times[k]) & (t < t_next)])
        # Events exactly at t_frame(k) open the window starting at k and are not in the one ending there.
        assert np.sum(window["t"] == times[k]) == 2
        if k:
            assert not np.any(reader.window(times[k - 1], times[k])["t"] == times[k])
        assert reader.index_of_time(times[k]) == np.searchsorted(t, times[k], side="left")
    # Windows at the other convention's frame times (and 1 us off) are read right too: the reader's
    # frame times are the ones its timeidx refers to.
    np.testing.assert_array_equal(reader.frame_times, times)
    other = [reference_time(k, "truncate" if convention == "round" else "round") for k in range(NUM_FRAMES)]
    for t_start in other + [time - 1 for time in other] + [time + 1 for time in times]:
        for t_end in (t_start + 1, t_start + 33_334):
            np.testing.assert_array_equal(reader.window(t_start, t_end)["t"], t[(t >= t_start) & (t < t_end)])


def test_a_file_that_no_entry_tells_apart_reads_as_round(tmp_path):
    t = np.array([5, 40_000, 40_001, 100_000, 150_000])  # nothing at a time where the conventions differ
    path = write_events(tmp_path / "v.h5", [1] * 5, [1] * 5, t, [0, 1, 0, 1, 0], num_frames=6)
    assert EventFile(path, num_frames=6).convention == "round"


def test_mixed_timeidx_fits_neither_convention(tmp_path):
    events = on_frame_events("truncate")
    t = events["t"]
    rounded = reference_timeidx(t, NUM_FRAMES, "round")
    truncated = reference_timeidx(t, NUM_FRAMES, "truncate")
    timeidx = np.concatenate([rounded[:10], truncated[10:]])  # frames 2, 5, 8 round; 11, 14, ... truncate
    path = tmp_path / "v.h5"
    write_by_hand(path, events, NUM_FRAMES, timeidx)
    a, b = reference_time(11, "truncate"), reference_time(11, "round")
    expected = (f"{path}: timeidx: entry 11 = {truncated[11]} fits neither frame-time convention; "
                f"expected {rounded[11]} (round: first event at or after {b} us) or {truncated[11]} "
                f"(truncate: first event at or after {a} us) (entry 2 rules out truncate)")
    with pytest.raises(DatasetFormatError) as info:
        EventFile(path, num_frames=NUM_FRAMES)
    assert str(info.value) == expected


def test_shifted_last_entry_fits_neither_and_check_reports_it(tmp_path):
    written = make_dataset(tmp_path, videos={"v": "train"}, num_frames=NUM_FRAMES, events_per_video=10)
    events = on_frame_events("truncate")
    t = events["t"]
    timeidx = reference_timeidx(t, NUM_FRAMES, "truncate")
    timeidx[-1] -= 1  # the last frame, which the opening check probes
    path = fmt.events_path(written.root, "train", "v")
    path.unlink()
    write_by_hand(path, events, NUM_FRAMES, timeidx)
    k, a, b = NUM_FRAMES - 1, reference_time(NUM_FRAMES - 1, "truncate"), reference_time(NUM_FRAMES - 1, "round")
    stated = (f"timeidx: entry {k} = {timeidx[k]} fits neither frame-time convention; expected "
              f"{np.searchsorted(t, b)} (round: first event at or after {b} us) or "
              f"{np.searchsorted(t, a)} (truncate: first event at or after {a} us)")
    with pytest.raises(DatasetFormatError, match=r"v\.h5: " + stated.replace("(", r"\(").replace(")", r"\)")):
        sample_set(written.root, "train")
    conventions = {}
    found = [str(p) for p in check_dataset(written.root, conventions=conventions)]
    assert found == [f"{path}: {stated}"]
    assert conventions == {path: None}


def test_full_check_reports_an_entry_the_opening_check_does_not_probe(tmp_path):
    written = make_dataset(tmp_path, videos={"v": "train"}, num_frames=NUM_FRAMES, events_per_video=10)
    events = on_frame_events("truncate")
    timeidx = reference_timeidx(events["t"], NUM_FRAMES, "truncate")
    timeidx[4] += 1  # frame 4: same time in both conventions, and not probed
    assert 4 not in probe_frames(NUM_FRAMES)
    path = fmt.events_path(written.root, "train", "v")
    path.unlink()
    write_by_hand(path, events, NUM_FRAMES, timeidx)
    assert EventFile(path, num_frames=NUM_FRAMES).convention == "truncate"
    found = [str(p) for p in check_dataset(written.root)]
    assert len(found) == 1 and found[0].startswith(f"{path}: timeidx: entry 4 = {timeidx[4]} fits neither")
    # Round disagrees at the 10 frames whose times differ (events lie on them) and at frame 4.
    assert found[0].endswith("entries disagreeing with events/t: 11 under round, 1 under truncate"), found


def test_dataset_and_check_use_each_files_own_convention(tmp_path, capsys):
    videos = {"r": "train", "t": "train", "plain": "valid"}
    written = make_dataset(tmp_path, videos=videos, num_frames=NUM_FRAMES, events_per_video=200)
    files = {v: fmt.events_path(tmp_path, "train", v) for v in ("r", "t")}
    events = {v: on_frame_events({"r": "round", "t": "truncate"}[v], seed=i) for i, v in enumerate(files)}
    for video, path in files.items():
        write_in_convention(path, events[video], {"r": "round", "t": "truncate"}[video])
    ds = sample_set(tmp_path, "train", image_age=1, event_span="window", window_us=34_000)
    for index in range(len(ds)):
        sample = ds[index]
        convention = {"r": "round", "t": "truncate"}[sample.video]
        k, t = sample.frame, events[sample.video]["t"]
        t_end = reference_time(k, convention)
        assert (sample.t_start_us, sample.t_end_us) == (t_end - 34_000, t_end)
        got = sample.events[:, 2].numpy().astype(np.int64) + sample.t_image_us
        np.testing.assert_array_equal(got, t[(t >= t_end - 34_000) & (t < t_end)])
        assert np.sum(got == reference_time(k - 1, convention)) == 2  # the window holds frame k - 1's time...
        assert not np.any(got == t_end)  # ...but not frame k's: those events open the next window
    conventions = {}
    assert check_dataset(tmp_path, conventions=conventions, decode_frames=True) == []
    assert conventions[files["r"]] == "round" and conventions[files["t"]] == "truncate"
    assert conventions[fmt.events_path(tmp_path, "valid", "plain")].startswith("round")
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert f"{files['t']}: frame times (timeidx): truncate\n" in out  # a file not in this package's convention
    assert f"{files['r']}: frame times" not in out and f"{fmt.events_path(tmp_path, 'valid', 'plain')}: frame" not in out
    count = sum(1 for c in conventions.values() if c.startswith("round"))
    assert (f"frame times (timeidx): round in {count} files (round(1e6 * k / fps), as this package writes); truncate "
            "in 1 file (int(1e6 * k / fps), the reference loader's). Each file is read in its own convention, so a mix "
            "is no problem\n") in out
    assert written.frames.keys() == videos.keys()
    undetermined = convention_lines({tmp_path / "a.h5": "round", tmp_path / "b.h5": None})
    assert undetermined == ["frame times (timeidx): round in 1 file (round(1e6 * k / fps), as this package writes); "
                            "not determined in 1 file (timeidx has a problem listed below)"]  # no mix, no line of b's
    assert convention_lines({tmp_path / "a.h5": "round"}) == [
        "frame times (timeidx): round in 1 file (round(1e6 * k / fps), as this package writes)"]


def test_opening_reads_only_a_bounded_part_of_t(tmp_path):
    num_frames, chunk = 2700, 1024
    rng = np.random.default_rng([5])
    t = np.sort(rng.integers(0, fmt.frame_time_us(num_frames), 300_000))
    ones = np.ones(len(t), np.int64)
    path = write_events(tmp_path / "big.h5", ones, ones, t, ones, num_frames=num_frames, compression="gzip",
                        chunk_events=chunk)
    probes = probe_frames(num_frames)
    assert len(probes) <= MAX_CONVENTION_PROBES + 3 and probes[-1] == num_frames - 1
    with h5py.File(path, "r") as h5:
        timeidx = h5[fmt.KEY_TIMEIDX][()]
        touched = {int(i) // chunk for k in probes for i in (timeidx[k] - 1, timeidx[k])}
        untouched = [c for c in range(5, len(t) // chunk - 5) if c not in touched]
        victim = untouched[len(untouched) // 2]
        info = h5[fmt.KEY_T].id.get_chunk_info(victim)
    with open(path, "r+b") as f:
        f.seek(info.byte_offset)
        f.write(b"\x00garbage" * (info.size // 8))
    reader = EventFile(path, num_frames=num_frames)  # does not touch the broken chunk
    assert reader.convention == "round"
    with pytest.raises(DatasetFormatError, match=r"big\.h5: events/t: cannot read entries"):
        reader.read(victim * chunk, (victim + 1) * chunk)
