"""A checkpoint is read in one place, into one typed object; an older one is upgraded there."""
from __future__ import annotations

import pytest
import torch

from dagr_lite.data.spec import SampleSpec
from dagr_lite.config import ConfigError
from dagr_lite.engine.checkpoint import Checkpoint, check_picture_layout, load_checkpoint, save_checkpoint
from dagr_lite.eval.operating import NMS_IOUS, UNMEASURED
from dagr_lite.nn.detector import Detector


def raw(path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=True)


def test_a_trained_checkpoint_reads_as_its_model_sample_and_operating_point(trained_checkpoints):
    path = trained_checkpoints["hybrid"]
    checkpoint = load_checkpoint(path)
    assert isinstance(checkpoint, Checkpoint) and checkpoint.path == path
    saved = raw(path)
    assert checkpoint.detector.as_dict() == saved["detector"]
    assert checkpoint.sample == SampleSpec(**{key: saved["config"]["data"][key] for key in SampleSpec.keys()})
    assert checkpoint.image_age == saved["config"]["data"]["image_age"] == 1
    assert checkpoint.operating.nms_iou in NMS_IOUS and checkpoint.operating.as_dict() == saved["operating"]
    assert checkpoint.model_name == "hybrid" and checkpoint.training["step"] == saved["step"] == 3
    model = checkpoint.model()
    assert isinstance(model, Detector)
    assert all(torch.equal(value, saved["ema"]["module"][key]) for key, value in model.state_dict().items())


def test_a_checkpoint_saved_before_later_keys_is_read_as_it_was_trained(trained_checkpoints, tmp_path):
    old = raw(trained_checkpoints["events_only"])
    del old["operating"], old["detector"]["geometry"], old["config"]["data"]["refractory_us"]
    path = tmp_path / "old.pt"
    save_checkpoint(path, {key: value for key, value in old.items() if key != "format"})
    checkpoint = load_checkpoint(path)
    assert checkpoint.operating == UNMEASURED
    assert checkpoint.detector.geometry is False and checkpoint.sample.refractory_us == 0


def test_a_checkpoint_that_cannot_be_read_is_named(trained_checkpoints, tmp_path):
    broken = raw(trained_checkpoints["events_only"])
    broken["config"]["data"]["window_us"] = -5
    path = tmp_path / "broken.pt"
    save_checkpoint(path, {key: value for key, value in broken.items() if key != "format"})
    with pytest.raises(ValueError, match=r"broken\.pt: its model, sample or operating point cannot be read "
                                         r"\(sample window_us must be a positive integer, got -5\)"):
        load_checkpoint(path)
    (tmp_path / "other.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match=r"other\.pt: cannot read as a dagr_lite checkpoint"):
        load_checkpoint(tmp_path / "other.pt")


def test_an_evaluation_may_change_a_pictures_window_length_not_its_channels():
    """Two carry pictures of 7 channels (recent window + moved frame, recent window + confirmed
    events) have one count; the layout check names the key that would swap them."""
    trained = {"event_picture": False, "carry_picture": True, "carry_recent_us": 20_000, "carry_confirm_us": 0,
               "carry_align_us": 5_000, "carry_spans_us": (33_333,), "carry_onset": True}
    check_picture_layout("m.pt", trained, {**trained, "carry_recent_us": 10_000, "carry_align_us": 3_000})
    with pytest.raises(ConfigError, match=r"m\.pt: data\.carry_confirm_us=5000 adds carry picture channels the model "
                                          r"was not trained with \(data\.carry_confirm_us=0\)"):
        check_picture_layout("m.pt", trained, {**trained, "carry_confirm_us": 5_000, "carry_align_us": 0})
    with pytest.raises(ConfigError, match=r"data\.carry_align_us=0 removes carry picture channels"):
        check_picture_layout("m.pt", trained, {**trained, "carry_align_us": 0})
    check_picture_layout("m.pt", trained, {**trained, "carry_spans_us": [33_333]})  # a config's list: the same
    with pytest.raises(ConfigError, match=r"m\.pt: data\.carry_spans_us=\[50000\] changes what the carry picture's "
                                          r"channels hold \(the model was trained with data\.carry_spans_us=\[33333\]\)"):
        check_picture_layout("m.pt", trained, {**trained, "carry_spans_us": [50_000]})
    with pytest.raises(ConfigError, match=r"data\.carry_onset=False changes what the carry picture's channels hold"):
        check_picture_layout("m.pt", trained, {**trained, "carry_onset": False})
    with pytest.raises(ConfigError, match=r"data\.event_picture=True changes the model's input"):
        check_picture_layout("m.pt", trained, {**trained, "event_picture": True})
    plain = {**trained, "carry_picture": False}  # no carry picture: its windows are read by nothing
    check_picture_layout("m.pt", plain, {**plain, "carry_confirm_us": 5_000})
    with pytest.raises(ConfigError, match=r"data\.carry_picture=True changes the model's input"):
        check_picture_layout("m.pt", plain, {**plain, "carry_picture": True})


def test_evaluate_and_the_sweep_check_an_overrides_value_before_the_pictures_channels(trained_checkpoints, tmp_path):
    """A bad value is named as a bad value (not as a change of the picture's channels), and a sweep
    of two checkpoints refuses the second's override before it scores the first."""
    from dagr_lite.apps.sweep import sweep
    from dagr_lite.config import compose_config
    from dagr_lite.engine.evaluate import evaluate
    from dagr_lite.errors import UserError

    hybrid = trained_checkpoints["hybrid"]
    with pytest.raises(ConfigError, match=r"data\.carry_recent_us must be an integer >= 0 .*got 'abc'"):
        evaluate(compose_config("evaluate", [f"ckpt={hybrid}", f"run_dir={tmp_path / 'e'}", "data.carry_recent_us=abc"]))
    with pytest.raises(UserError, match=r"sample carry_recent_us must be an integer >= 0, got -5"):
        sweep(compose_config("sweep", [f"ckpt=[{hybrid}]", f"out={tmp_path / 's'}", "data.carry_recent_us=-5"]))
    scored = []
    import dagr_lite.apps.sweep as sweep_module
    real = sweep_module.sweep_checkpoint
    sweep_module.sweep_checkpoint = lambda *args, **kwargs: scored.append(1) or real(*args, **kwargs)
    try:  # the events-only model reads no carry picture: turning one on is refused for it, before anything is scored
        with pytest.raises(ConfigError, match=r"events_only.*data\.carry_picture=True changes the model's input"):
            sweep(compose_config("sweep", [f"ckpt=[{hybrid},{trained_checkpoints['events_only']}]",
                                           f"out={tmp_path / 't'}", "data.carry_picture=true"]))
    finally:
        sweep_module.sweep_checkpoint = real
    assert not scored and not (tmp_path / "t").exists()
