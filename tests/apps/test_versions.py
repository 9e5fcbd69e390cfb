"""The version experiment's plumbing: source, builds, training, evaluation and the table, with tiny budgets."""
import json
from pathlib import Path

import pytest

from dagr_lite.apps.versions import main, run_versions, write_stub_source


def test_versions_table_from_one_source_and_reuse(tmp_path):
    frames, labels, splits = write_stub_source(tmp_path / "source", 180, 320, seconds=0.2,
                                               splits={"train": 2, "valid": 1, "test": 1})
    assert json.loads(splits.read_text()) == {"train": ["source_000", "source_001"], "valid": ["source_002"],
                                              "test": ["source_003"]}
    tiny = ["loader.batch_size=4", "loader.num_workers=0"]
    rows = run_versions(frames, tmp_path / "out", ["v2", "v3"], minutes=1.0, labels=labels, splits=splits, steps=1,
                        train_overrides=tiny)
    assert [(r["version"], r["scale"], r["upsample"], r["dvs_model"]) for r in rows] == [("v2", 4, 1, "clean"),
                                                                                         ("v3", 2, 1, "clean")]
    for row in rows:
        assert all(-1 <= row[m] <= 1 for m in ("AP50", "AP75", "mAP"))
        test_split = tmp_path / "out" / "datasets" / row["version"] / "test" / "events"
        assert [p.stem for p in test_split.glob("*.h5")] == ["source_003"]  # the same test video for every version
    saved = json.loads((tmp_path / "out" / "versions.json").read_text())
    assert saved["rows"] == json.loads(json.dumps(rows))
    assert "| v3 | 1 | 2 | clean |" in (tmp_path / "out" / "versions.md").read_text()
    stamp = (tmp_path / "out" / "runs" / "v2" / "checkpoints" / "best.pt").stat().st_mtime
    again = run_versions(frames, tmp_path / "out", ["v2"], minutes=1.0, labels=labels, splits=splits, steps=1,
                         train_overrides=tiny)  # reused: no new build or training
    assert (tmp_path / "out" / "runs" / "v2" / "checkpoints" / "best.pt").stat().st_mtime == stamp
    assert again[0]["AP50"] == rows[0]["AP50"]
    with pytest.raises(ValueError, match=r"--versions: unknown \[.v9.\]"):
        run_versions(frames, tmp_path / "x", ["v9"], minutes=1.0)


def test_stub_source_is_reused_only_with_its_own_settings(tmp_path):
    few = {"train": 1, "valid": 1, "test": 1}
    frames, labels, _ = write_stub_source(tmp_path, 36, 64, seconds=0.1, splits=few)
    assert json.loads((tmp_path / "source.json").read_text()) == {"height": 36, "width": 64, "seconds": 0.1,
                                                                 "videos": few}
    assert len(list((frames / "source_000").glob("*.jpg"))) == 3  # 0.1 s at 30 fps
    stamp = labels.stat().st_mtime
    assert write_stub_source(tmp_path, 36, 64, seconds=0.1, splits=few)[1].stat().st_mtime == stamp  # reused
    with pytest.raises(ValueError, match="made with .*choose another --out"):
        write_stub_source(tmp_path, 72, 128, seconds=0.1, splits=few)


@pytest.mark.parametrize("option, value, expected", [("--stub-source", "1280", "WxH"),
                                                     ("--stub-source", "0x720", "WxH"),
                                                     ("--stub-videos", "12,2", "TRAIN,VALID,TEST"),
                                                     ("--stub-videos", "a,b,c", "TRAIN,VALID,TEST")])
def test_bad_stub_source_options_are_named(tmp_path, option, value, expected):
    args = {"--stub-source": "64x36", "--stub-videos": "1,1,1", option: value}
    argv = [*(x for kv in args.items() for x in kv), "--budget-minutes", "1", "--out", str(tmp_path)]
    with pytest.raises(SystemExit, match=f"{option}: expected {expected}"):
        main(argv)
    assert not (tmp_path / "source").exists()


@pytest.mark.parametrize("option, value, expected", [("--versions", "v9", r"--versions: unknown \['v9'\]"),
                                                     ("--versions", "", "--versions: expected some of"),
                                                     ("--budget-minutes", "0", "--budget-minutes: expected a positive"),
                                                     ("--steps", "0", "--steps: expected a positive")])
def test_the_experiment_checks_its_arguments_before_any_work(tmp_path, option, value, expected):
    args = {"--stub-source": "64x36", "--stub-videos": "1,1,1", "--budget-minutes": "1", option: value}
    with pytest.raises(SystemExit, match=expected):
        main([*(x for kv in args.items() for x in kv), "--out", str(tmp_path)])
    assert list(tmp_path.iterdir()) == []  # nothing rendered, built or trained


def test_versions_train_with_the_quick_recipe_itself(tmp_path):
    """Every key the quick recipe sets has the recipe's value in a version's training config, but
    the length, which the budget replaces (and the validation and picture intervals)."""
    from omegaconf import OmegaConf

    from dagr_lite.config import compose_config
    from dagr_lite.apps.versions import version_config

    recipe = OmegaConf.load(Path(__file__).resolve().parents[2] / "conf" / "recipe" / "quick.yaml")
    stub = compose_config("train", [])
    ours = version_config(tmp_path / "root", tmp_path / "run", minutes=4.0, steps=None, seed=0)
    budget = {"trainer.max_steps", "trainer.max_epochs", "trainer.max_minutes", "trainer.schedule_by",
              "trainer.val_every", "trainer.image_every"}
    keys = [f"{group}.{key}" for group, values in recipe.items() for key in values]
    assert ours.data.max_events == stub.data.max_events
    for key in keys:
        if key not in budget:
            assert OmegaConf.select(ours, key) == OmegaConf.select(stub, key), key
    assert ours.trainer.max_minutes == 4.0 and ours.trainer.schedule_by == "time"
