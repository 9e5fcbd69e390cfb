"""The ego dataset: valid, deterministic, and hard in the ways it claims (camera motion, flicker,
hands that rest and leave, occlusion, noisy events), with boxes that hold each hand's visible pixels."""
from pathlib import Path

import numpy as np
import pytest
import yaml

from dagr_lite.data import format as fmt
from dagr_lite.data.check import check_dataset
from dagr_lite.data.events import EventFile
from dagr_lite.synth import ego
from dagr_lite.synth.dvs import LUMA_WEIGHTS as LUMA
from dagr_lite.synth.ego import EgoScene, generate_ego
from dagr_lite.synth.stub import generate_stub, generation_workers, split_of_videos
from tests.settings import sample_set


def test_ego_is_a_valid_dataset_whose_videos_are_each_clean_or_noisy(tmp_path):
    root = generate_ego(tmp_path / "ego", seconds=0.5, splits={"train": 2, "valid": 1}, progress=False)
    assert check_dataset(root, decode_frames=True) == []
    ds = sample_set(root, "train", image_size=(180, 320))
    assert len(ds) == 2 * 14
    assert sum(len(ds[i].boxes) for i in range(len(ds))) > 0
    # The same scenes with every video clean or noisy (other events: noise, leak, a 30 Hz bandwidth), and
    # mixed gives each video exactly one of the two.
    counts = {}
    for model in ("clean", "noisy", "mixed"):
        out = generate_ego(tmp_path / model, seconds=0.3, splits={"train": 2}, dvs_model=model, progress=False)
        counts[model] = [EventFile(fmt.events_path(out, "train", f"ego_{i:03d}")).read(0, 10**9)["t"].size
                         for i in range(2)]
    assert all(n != c for n, c in zip(counts["noisy"], counts["clean"]))
    assert all(m in (c, n) for m, c, n in zip(counts["mixed"], counts["clean"], counts["noisy"]))


def test_generation_is_deterministic(tmp_path):
    a = generate_ego(tmp_path / "a", seconds=0.2, splits={"train": 1}, progress=False)
    b = generate_ego(tmp_path / "b", seconds=0.2, splits={"train": 1}, progress=False)
    read = lambda root: EventFile(fmt.events_path(root, "train", "ego_000")).read(0, 10**9)  # noqa: E731
    for name in "xytp":
        np.testing.assert_array_equal(read(a)[name], read(b)[name])
    assert (a / fmt.LABELS_FILE).read_text() == (b / fmt.LABELS_FILE).read_text()


def test_worker_processes_write_the_dataset_one_process_writes(tmp_path):
    # Segments in which a split comes back: videos are named in order across them, so a version that appends
    # training videos after the test videos leaves every earlier video (and its name) as it was.
    splits = [("train", 2), ("test", 1), ("train", 1)]
    one = generate_ego(tmp_path / "one", seconds=0.2, splits=splits, progress=False, workers=1)
    two = generate_ego(tmp_path / "two", seconds=0.2, splits=splits, progress=False, workers=2)
    assert sorted(p.stem for p in (one / "train" / "events").iterdir()) == ["ego_000", "ego_001", "ego_003"]
    assert [p.stem for p in (one / "test" / "events").iterdir()] == ["ego_002"]
    for split, video in (("train", "ego_000"), ("test", "ego_002"), ("train", "ego_003")):
        a = EventFile(fmt.events_path(one, split, video)).read(0, 10**9)
        b = EventFile(fmt.events_path(two, split, video)).read(0, 10**9)
        assert a["t"].size > 0
        for name in "xytp":
            np.testing.assert_array_equal(a[name], b[name])
    assert (one / fmt.LABELS_FILE).read_text() == (two / fmt.LABELS_FILE).read_text()
    # The first videos of a longer list are those of the shorter one.
    short = generate_ego(tmp_path / "short", seconds=0.2, splits={"train": 2}, progress=False)
    np.testing.assert_array_equal(EventFile(fmt.events_path(short, "train", "ego_001")).read(0, 10**9)["t"],
                                  EventFile(fmt.events_path(one, "train", "ego_001")).read(0, 10**9)["t"])


def test_split_lists_and_worker_counts_are_checked():
    assert split_of_videos({"train": 2, "valid": 1}) == ["train", "train", "valid"]
    assert split_of_videos([("train", 1), ("test", 2), ("train", 1)]) == ["train", "test", "test", "train"]
    with pytest.raises(ValueError, match="'val'"):
        split_of_videos({"val": 2})
    with pytest.raises(ValueError, match="workers must be at least 1"):
        generation_workers(4, 0)
    assert generation_workers(3, 8) == 3 and generation_workers(0, None) == 1 and generation_workers(1, None) == 1
    assert ego.EGO_VERSION == 4 and split_of_videos(ego.EGO_SPLITS)[:68] == split_of_videos(
        {"train": 48, "valid": 4, "test": 16})  # version 2's videos keep their names and splits


def test_the_camera_pans_by_several_pixels_a_frame_and_the_light_flickers():
    speeds, flickering = [], 0
    for seed in range(8):
        scene = EgoScene(seed)
        path = np.array([scene.camera(k / scene.fps) for k in range(scene.num_frames)])
        speeds.append(np.abs(np.diff(path, axis=0)).max(axis=1))
        flickering += scene.flicker_amp > 0
    speeds = np.concatenate(speeds)
    assert np.median(speeds) >= 2 and speeds.max() >= 6  # pans of several pixels a frame, not a jitter
    assert flickering >= 4


def test_hands_rest_leave_and_come_back():
    rests = returns = 0
    for seed in range(8):
        scene = EgoScene(seed)
        for i, hand in enumerate(scene.hand, start=1):
            times = np.arange(scene.num_frames) / scene.fps
            centres = np.array([scene._position(hand, t) for t in times])
            moved = np.linalg.norm(np.diff(centres, axis=0), axis=1)
            rests += np.any(moved < 1e-9)
            visible = [np.count_nonzero(scene.paint(t)[1] == i) >= ego.MIN_VISIBLE_PIXELS for t in times]
            gone = np.flatnonzero(~np.array(visible))
            returns += len(gone) > 0 and gone[0] > 0 and any(visible[gone[0]:])
    assert rests >= 4 and returns >= 1


def test_boxes_hold_each_hands_visible_pixels_and_occlusion_hides_them():
    occluded = 0
    for seed in range(6):
        scene = EgoScene(seed)
        for k in range(0, scene.num_frames, 5):
            image, owner = scene.paint(k / scene.fps)
            boxes = scene.boxes(k)
            shown = [i for i in range(1, len(scene.hand) + 1) if np.count_nonzero(owner == i) >= ego.MIN_VISIBLE_PIXELS]
            assert len(boxes) <= len(shown)
            for x, y, w, h in boxes.astype(int):  # tight: the visible pixels touch every edge
                inside = owner[y:y + h, x:x + w] > 0
                assert inside[0].any() and inside[-1].any() and inside[:, 0].any() and inside[:, -1].any()
            if scene.occluder is not None:
                (cx, cy), (hw, hh) = scene._occluder(k / scene.fps)
                r0, r1 = max(int(cy - hh), 0), min(int(np.ceil(cy + hh)), scene.height)
                c0, c1 = max(int(cx - hw), 0), min(int(np.ceil(cx + hw)), scene.width)
                assert not owner[r0:r1, c0:c1].any()  # nothing behind the object counts as hand
                occluded += 1
    assert occluded > 0


def test_luma_contrast_is_the_log_ratio_of_a_hand_to_its_surroundings_in_thresholds():
    # Hands of one known skin over a flat world, without flicker: every contrast is a per-pixel
    # loop's over the painted scene, lies within what the hands' shading allows (0.7 to 1 of the skin
    # towards the rim), and does not change with the light, which scales hand and world alike.
    scene = EgoScene(3)
    world_rgb, skin = np.array([90.0, 100.0, 110.0], np.float32), np.array([200.0, 140.0, 100.0], np.float32)
    scene.world[:] = world_rgb
    scene.flicker_amp, scene.occluder = 0.0, None
    for hand in scene.hand:
        hand["skin"], hand["sleeve"] = skin, None
    low, high = (np.log(np.array([0.7, 1.0]) * (skin @ LUMA) / (world_rgb @ LUMA)) / 0.2)
    seen = 0
    for k in range(0, scene.num_frames, 7):
        boxes, contrasts = scene.boxes(k), scene.luma_contrasts(k)
        assert contrasts.shape == (len(boxes),)
        image, owner = scene.paint(k / scene.fps)
        luma = np.maximum(image.astype(np.float64) @ LUMA, 20.0)
        for (x, y, w, h), contrast in zip(boxes.astype(int), contrasts):
            index = np.bincount(owner[y:y + h, x:x + w].ravel(), minlength=2)[1:].argmax() + 1
            around = []
            for r in range(max(y - 6, 0), min(y + h + 6, scene.height)):
                for c in range(max(x - 6, 0), min(x + w + 6, scene.width)):
                    if owner[r, c] == 0:
                        around.append(luma[r, c])
            hand = luma[owner == index]
            reference = abs(np.log(np.mean(hand) / np.mean(around))) / 0.2 if len(around) >= 30 else np.nan
            np.testing.assert_allclose(contrast, reference, rtol=1e-5)  # float32 luma against float64
            if np.isfinite(contrast):
                assert low - 1e-6 <= contrast <= high + 1e-6
                seen += 1
        np.testing.assert_allclose(scene.luma_contrasts(k, threshold=0.1), 2 * contrasts, rtol=1e-9)
    assert seen > 0
    before = [scene.luma_contrasts(k) for k in range(0, scene.num_frames, 7)]
    scene.light_phase += 1.5
    for k, contrasts in zip(range(0, scene.num_frames, 7), before):
        np.testing.assert_allclose(scene.luma_contrasts(k), contrasts, rtol=1e-5)


def test_ego_has_skin_coloured_background_and_moves_more_than_the_stub(tmp_path):
    """More events per second than the stub (its background holds still): the camera's motion is in them."""
    stub = generate_stub(tmp_path / "stub", seconds=0.3, splits={"train": 2}, progress=False)
    hard = generate_ego(tmp_path / "ego", seconds=0.3, splits={"train": 2}, dvs_model="clean", progress=False)
    count = lambda root, name: sum(EventFile(fmt.events_path(root, "train", f"{name}_{i:03d}")).read(0, 10**9)["t"].size
                                   for i in range(2))  # noqa: E731
    assert count(hard, "ego") > 1.5 * count(stub, "stub")
    world = EgoScene(0).world
    skin_like = (world[..., 0] > world[..., 2] + 20) & (world[..., 0] > world[..., 1] + 10)
    assert skin_like.mean() > 0.005


def test_ego_config_describes_the_generated_data():
    conf = yaml.safe_load((Path(__file__).resolve().parents[2] / "conf" / "dataset" / "ego.yaml").read_text())
    assert (conf["height"], conf["width"]) == (ego.EGO_HEIGHT, ego.EGO_WIDTH)
    assert (conf["upsample"], conf["dvs_model"]) == (ego.EGO_UPSAMPLE, ego.EGO_DVS_MODEL)
    assert conf["name"] == "ego" and conf["root"] is None


def test_the_generation_script_refuses_a_worker_count_below_one(tmp_path, capsys):
    import importlib.util
    spec = importlib.util.spec_from_file_location("generate", Path(__file__).parents[2] / "data_stubs" / "generate.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main([str(tmp_path / "out"), "--dataset", "ego", "--workers", "0"]) == 1
    assert "--workers must be at least 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
