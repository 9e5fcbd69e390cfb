import numpy as np

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.events import EventFile
from dagr_lite.synth.stub import HandScene, generate_stub
from tests.settings import sample_set


def test_stub_is_a_valid_dataset_with_hands_and_events(tmp_path):
    root = generate_stub(tmp_path / "stub", seconds=1.0, splits={"train": 2, "valid": 1}, progress=False)
    assert check_dataset(root, decode_frames=True) == []
    ds = sample_set(root, "train", image_size=(180, 320))
    assert len(ds) == 2 * 29
    samples = [ds[i] for i in range(len(ds))]
    assert max(len(s.boxes) for s in samples) >= 2 and min(len(s.events) for s in samples) > 0
    # Events concentrate on the hands: the event density inside boxes is well above the rest.
    inside = total = area = 0
    for s in samples:
        mask = np.zeros((180, 320), bool)
        for x1, y1, x2, y2 in s.boxes.numpy():
            mask[int(y1):int(np.ceil(y2)), int(x1):int(np.ceil(x2))] = True
        e = s.events.numpy().astype(int)
        inside += mask[e[:, 1], e[:, 0]].sum()
        total += len(e)
        area += mask.mean()
    assert inside / total > 3 * (area / len(samples))


def test_generation_is_deterministic(tmp_path):
    a = generate_stub(tmp_path / "a", seconds=0.3, splits={"train": 1}, progress=False)
    b = generate_stub(tmp_path / "b", seconds=0.3, splits={"train": 1}, progress=False)
    c = generate_stub(tmp_path / "c", seconds=0.3, splits={"train": 1}, seed=1, progress=False)
    read = lambda root: EventFile(fmt.events_path(root, "train", "stub_000")).read(0, 10**9)  # noqa: E731
    ea, eb, ec = read(a), read(b), read(c)
    for name in "xytp":
        np.testing.assert_array_equal(ea[name], eb[name])
    assert len(ec["t"]) != len(ea["t"]) or not np.array_equal(ec["x"], ea["x"])
    assert (a / fmt.LABELS_FILE).read_text() == (b / fmt.LABELS_FILE).read_text()


def test_scene_moves_fast_enough_that_a_stale_image_is_wrong():
    shifts = []
    for seed in range(4):
        scene = HandScene(seed, seconds=1.0)
        for k in range(1, scene.num_frames):
            now, before = scene.boxes(k), scene.boxes(k - 1)
            if len(now) == len(before) and len(now):
                centres = lambda b: b[:, :2] + b[:, 2:] / 2  # noqa: E731
                shifts += np.abs(centres(now) - centres(before)).max(axis=1).tolist()
    shifts = np.array(shifts)
    assert np.median(shifts) >= 2 and shifts.max() >= 8  # a few to tens of pixels per frame
    counts = [len(HandScene(seed).boxes(k)) for seed in range(4) for k in range(0, 90, 5)]
    assert min(counts) <= 1 and max(counts) >= 3  # hands leave and enter the frame


def test_stub_config_describes_the_generated_data():
    from pathlib import Path

    import yaml

    from dagr_lite.synth import stub
    conf = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "dataset" / "stub.yaml").read_text())
    assert (conf["height"], conf["width"]) == (stub.STUB_HEIGHT, stub.STUB_WIDTH)
    assert (conf["upsample"], conf["dvs_model"]) == (stub.STUB_UPSAMPLE, stub.STUB_DVS_MODEL)


def test_boxes_are_the_rendered_hands_pixels():
    """Every pixel a hand paints lies in a box, each box is tight around the hand pixels it holds,
    and boxes lie inside the frame (the scene's properties, whatever its random draws)."""
    from dagr_lite.synth.stub import MIN_BOX_SIZE

    for seed in range(3):
        scene = HandScene(seed, seconds=1.0)
        empty = HandScene(seed, seconds=1.0)
        empty._ellipses = lambda t: []  # the same background, light and shake, without hands
        for k in range(0, scene.num_frames, 6):
            hand = np.abs(scene.frame(k) - empty.frame(k)).max(axis=2) > 0.5
            boxes = scene.boxes(k)
            assert np.all(boxes[:, :2] >= 0) and np.all(boxes[:, 0] + boxes[:, 2] <= scene.width + 1e-9)
            assert np.all(boxes[:, 1] + boxes[:, 3] <= scene.height + 1e-9)
            covered = np.zeros_like(hand)
            for x, y, w, h in boxes:
                inside = np.zeros_like(hand)
                inside[int(y):int(np.ceil(y + h)), int(x):int(np.ceil(x + w))] = True
                covered |= inside
                rows, cols = np.nonzero(hand & inside)
                assert len(rows), (seed, k)
                if x > 0 and y > 0 and x + w < scene.width and y + h < scene.height:  # (a cut hand's box is
                    # its whole outline clipped, looser than the part seen)
                    gaps = [cols.min() - x, x + w - (cols.max() + 1), rows.min() - y, y + h - (rows.max() + 1)]
                    assert max(gaps) < 2.5, (seed, k, gaps)  # tight: a hand pixel within 2.5 px of each edge
            margin = int(np.ceil(MIN_BOX_SIZE)) + 1  # hands cut to slivers at the border have no box
            assert not np.any((hand & ~covered)[margin:-margin, margin:-margin]), (seed, k)
