"""Every option of every config group composes and resolves; bad configs fail at once."""
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException

import torch

from dagr_lite.config import (ConfigError, build_dataset, build_model, build_optimizer, check_values, detector_config,
                              resolve_config)
from dagr_lite.synth.build import VERSIONS
from dagr_lite.synth.egohands import EGOHANDS_HEIGHT, EGOHANDS_WIDTH

CONF = Path(__file__).resolve().parents[1] / "conf"


def options(group):
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def compose_cfg(name, overrides=()):
    with initialize_config_dir(config_dir=str(CONF), version_base=None):
        return compose(config_name=name, overrides=list(overrides))


def test_groups_hold_the_expected_options():
    assert options("dataset") == ["custom", "ego", "stub", "v1", "v2", "v3", "v4", "v5", "v6"]
    assert {"hybrid", "events_only", "image_only"} <= set(options("model"))
    assert options("optim") == ["adamw", "sgd"] and options("recipe") == ["ego", "quick", "stub"]
    assert options("data") == options("loader") == options("eval") == ["default"]


@pytest.mark.parametrize("config,group", [("train", "dataset"), ("train", "model"), ("train", "optim"),
                                          ("evaluate", "dataset")])
def test_every_option_composes_and_resolves(config, group, tmp_path):
    extra = [f"ckpt={tmp_path / 'last.pt'}"] if config == "evaluate" else []
    for option in options(group):
        cfg = resolve_config(compose_cfg(config, [f"{group}={option}", f"dataset.root={tmp_path}", *extra]))
        if group == "optim":  # an optimiser config names its class
            assert type(build_optimizer(cfg, [torch.nn.Parameter(torch.zeros(1))])).__name__.lower() == option
        else:
            assert cfg[group].name == option
        assert cfg.dataset.root == str(tmp_path)


def test_built_in_datasets_train_with_the_quick_recipe():
    quick = resolve_config(compose_cfg("train", ["dataset=custom", "dataset.root=/data/mine", "recipe=quick"]))
    for name in ("stub", "ego"):
        cfg = resolve_config(compose_cfg("train", [f"dataset={name}"]))
        assert cfg.dataset.name == name and cfg.dataset.root is None
        assert cfg.optim == quick.optim
        # the same recipe; the ego dataset's busier samples have a larger wall-clock cap
        budget = {"max_minutes": 13.0} if name == "ego" else {}
        assert cfg.trainer == {**quick.trainer, **budget}
        assert cfg.data.augment == quick.data.augment and quick.data.augment.crop == 0.5
    assert quick.trainer.max_minutes == 9.0


def test_default_dataset_is_the_stub_with_its_short_recipe():
    cfg = resolve_config(compose_cfg("train"))
    assert cfg.dataset.name == "stub" and cfg.dataset.root is None
    assert (cfg.dataset.height, cfg.dataset.width) == (180, 320)
    assert cfg.optim.lr == pytest.approx(1e-3) and cfg.trainer.max_epochs == 40 and cfg.loader.batch_size == 16
    paper = resolve_config(compose_cfg("train", ["dataset=v6", "dataset.root=/data/v6"]))
    assert paper.optim.lr == pytest.approx(2e-4) and paper.trainer.max_steps == 100_000  # the paper's recipe
    assert resolve_config(compose_cfg("train", ["optim.lr=5e-4"])).optim.lr == pytest.approx(5e-4)


@pytest.mark.parametrize("version", sorted(VERSIONS))
def test_versions_read_at_the_resolution_the_builder_makes_and_the_root_from_the_environment(version, monkeypatch,
                                                                                              tmp_path):
    monkeypatch.setenv("EVENTEGOHANDS_ROOT", str(tmp_path))
    cfg = resolve_config(compose_cfg("train", [f"dataset={version}"]))
    d = cfg.dataset
    scale = VERSIONS[version]["scale"]  # the builder's table owns how each version is made
    assert (d.height, d.width) == (EGOHANDS_HEIGHT // scale, EGOHANDS_WIDTH // scale)
    assert d.root == str(tmp_path / version)
    override = resolve_config(compose_cfg("train", [f"dataset={version}", "dataset.root=/data/x"]))
    assert override.dataset.root == "/data/x"


def test_unset_root_names_the_variable_and_the_override():
    with pytest.raises(ConfigError, match=r"EVENTEGOHANDS_ROOT.*dataset\.root=/path/to/v6"):
        resolve_config(compose_cfg("train", ["dataset=v6"]))
    with pytest.raises(ConfigError, match=r"dataset\.root"):
        resolve_config(compose_cfg("train", ["dataset=custom"]))


def test_unknown_keys_fail_at_composition():
    with pytest.raises(ConfigCompositionException):
        compose_cfg("train", ["data.windw_us=10"])
    with pytest.raises(ConfigCompositionException):
        compose_cfg("train", ["dataset=v7"])


def test_inconsistent_values_fail(tmp_path):
    with pytest.raises(ConfigError, match=r"dataset\.height"):
        resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={tmp_path}", "dataset.height=10"]))
    cfg = resolve_config(compose_cfg("train", ["dataset=v6", f"dataset.root={tmp_path / 'absent'}"]))
    with pytest.raises(ConfigError, match=r"dataset\.root=.*absent of v6 is not a folder"):
        build_dataset(cfg, "train", train=True, with_image=True)


def test_custom_dataset_takes_its_resolution_from_the_frames(dataset):
    cfg = resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={dataset.root}"]))
    ds = build_dataset(cfg, "train", train=True, with_image=True)
    assert ds.image_size == (48, 64) and ds.transform is not None
    assert build_dataset(cfg, "valid", train=False, with_image=True).transform is None
    wrong = resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={dataset.root}",
                                                 "dataset.height=360", "dataset.width=640"]))
    with pytest.raises(ValueError, match=r"frame_0.jpg: frame is 64x48 \(WxH\), expected 640x360 as the dataset is "
                                         r"configured"):
        build_dataset(wrong, "train", train=True, with_image=True)
    v6 = resolve_config(compose_cfg("train", ["dataset=v6", f"dataset.root={dataset.root}"]))
    with pytest.raises(ValueError, match=r"expected 640x360 as the dataset is configured"):
        build_dataset(v6, "train", train=True, with_image=True)


def test_the_dataset_line_says_what_the_model_reads(dataset):
    from dagr_lite.engine.checkpoint import describe_dataset
    cfg = resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={dataset.root}"]))
    window, context = cfg.data.window_us, cfg.data.context_us

    def head(ds):
        return f"{dataset.root} [valid]: {len(ds.videos)} videos, {len(ds)} samples, 64x48 px"

    hybrid = build_dataset(cfg, "valid", train=False, with_image=True, image_age=3)
    assert hybrid.carry_picture  # the default hybrid's carry branch reads it
    assert describe_dataset(hybrid) == (f"{head(hybrid)}, image age 3 frames, events of the last {window} us "
                                        f"(none from before the image - {context} us), a picture of every event "
                                        "since the image")
    only = resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={dataset.root}", "model=image_only"]))
    plain = build_dataset(only, "valid", train=False, with_image=True, image_age=3)
    assert describe_dataset(plain, events=False) == f"{head(plain)}, image age 3 frames"  # image_only
    frameless = build_dataset(cfg, "valid", train=False, with_image=False)  # events_only
    assert describe_dataset(frameless, image=False) == f"{head(frameless)}, events of the last {window} us"
    peer = resolve_config(compose_cfg("train", ["dataset=custom", f"dataset.root={dataset.root}", "model=image_only",
                                                "data.event_picture=true"]))
    pictured = build_dataset(peer, "valid", train=False, with_image=True)  # the dense peer
    assert describe_dataset(pictured, events=False) == (f"{head(pictured)}, the image a picture of the events of "
                                                        f"the last {window} us")


def test_model_sizes_build_and_differ():
    sizes = {}
    for size in ("s", "m"):
        cfg = resolve_config(compose_cfg("train", [f"model.size={size}"]))
        sizes[size] = sum(p.numel() for p in build_model(cfg, height=180, width=320).parameters())
    assert sizes["m"] > 1.5 * sizes["s"]
    with pytest.raises(ConfigError, match="model.size"):
        build_model(resolve_config(compose_cfg("train", ["model.size=xl"])), height=180, width=320)


def test_train_and_evaluate_share_the_data_loader_and_eval_groups(tmp_path):
    train = resolve_config(compose_cfg("train"))
    evaluate = resolve_config(compose_cfg("evaluate", [f"ckpt={tmp_path / 'x.pt'}"]))
    assert train.loader == evaluate.loader and train.eval == evaluate.eval
    assert set(train.data) == set(evaluate.data) and set(train.data.augment) == set(evaluate.data.augment)
    from omegaconf import OmegaConf
    recipe = OmegaConf.load(CONF / "recipe" / "quick.yaml").data.augment  # the stub's recipe sets these for training
    assert {k: v for k, v in train.data.augment.items() if k not in recipe} == \
        {k: v for k, v in evaluate.data.augment.items() if k not in recipe}
    assert all(train.data.augment[k] == v for k, v in recipe.items())
    # evaluation takes what defines a sample from the checkpoint unless a value is given
    assert evaluate.data.window_us is None and evaluate.data.image_age is None and evaluate.graph.radius is None


def test_the_optim_group_chooses_the_optimiser():
    params = [torch.nn.Parameter(torch.zeros(3))]
    adamw = build_optimizer(resolve_config(compose_cfg("train", ["optim.lr=3e-4"])), params)
    assert type(adamw) is torch.optim.AdamW and adamw.param_groups[0]["lr"] == pytest.approx(3e-4)
    assert adamw.param_groups[0]["betas"] == (0.9, 0.999)
    sgd = build_optimizer(resolve_config(compose_cfg("train", ["optim=sgd"])), params)
    assert type(sgd) is torch.optim.SGD and sgd.param_groups[0]["nesterov"]
    with pytest.raises(ConfigError, match="optim"):
        build_optimizer(resolve_config(compose_cfg("train", ["optim.lr=-1"])), params)


def test_model_defaults_come_from_conf_and_variants_inherit_them():
    hybrid = detector_config(resolve_config(compose_cfg("train")), height=180, width=320)
    assert hybrid.strides == (8, 16, 32) and hybrid.event_channels == (16, 32, 48, 64) and hybrid.time_scale_us == 1e5
    assert hybrid.event_dense == 0  # GCN blocks over the pooled graphs
    assert hybrid.graph.as_dict() == {"radius": 5.0, "beta": 5e-4, "max_neighbors": 16}
    events = detector_config(resolve_config(compose_cfg("train", ["model=events_only"])), height=180, width=320)
    assert not events.use_image and events.use_events
    # a smaller graph than the hybrid's; beta is the hybrid's, and any key can still be overridden
    assert events.graph.as_dict() == {"radius": 3.0, "beta": 5e-4, "max_neighbors": 8}
    wider = detector_config(resolve_config(compose_cfg("train", ["model=events_only", "model.graph.radius=4"])),
                            height=180, width=320)
    assert wider.graph.radius == 4.0 and wider.graph.max_neighbors == 8
    # the events-only model reads its nodes as a CNN reads a picture, as wide as the image CNN
    assert events.event_channels == (16, 64, 128, 256) and events.event_dense == 4
    assert (events.image_width, events.head_hidden) == (hybrid.image_width, hybrid.head_hidden)
    sized = detector_config(resolve_config(compose_cfg("train", ["model=events_only", "model.size=m"])),
                            height=180, width=320)
    assert sized.event_channels == (24, 96, 192, 384) and sized.image_width == 24
    image = detector_config(resolve_config(compose_cfg("train", ["model=image_only"])), height=180, width=320)
    assert image.graph is None and not image.use_events
    with pytest.raises(ConfigError, match=r"model\.graph radius must be a positive number, got -1"):
        build_model(resolve_config(compose_cfg("train", ["model.graph.radius=-1"])), height=180, width=320)
    # The hybrid's carry branch reads the picture, which the sample then holds; the other models have none.
    assert (hybrid.carry_width, hybrid.image_channels) == (8, 3) and compose_cfg("train").data.carry_picture is True
    assert (hybrid.carry_channels, hybrid.carry_frame) == (4, True)  # the frame beside a picture with a recent channel
    assert (events.carry_width, image.carry_width, image.image_channels) == (0, 0, 3)
    for variant in ("events_only", "image_only"):
        assert resolve_config(compose_cfg("train", [f"model={variant}"])).data.carry_picture is False
    peer = detector_config(resolve_config(compose_cfg("train", ["model=image_only", "data.carry_picture=true"])),
                           height=180, width=320)
    assert (peer.carry_width, peer.image_channels) == (0, 7)  # the image branch reads it
    early = detector_config(resolve_config(compose_cfg("train", ["model.carry_width=0", "data.carry_picture=true"])),
                            height=180, width=320)
    assert (early.carry_width, early.image_channels) == (0, 7)
    with pytest.raises(ConfigError, match=r"model\.carry_width=8 .* needs data\.carry_picture=true"):
        detector_config(resolve_config(compose_cfg("train", ["data.carry_picture=false"])), height=180, width=320)
    # The event head's answers: a hybrid's, with its event head; a single-branch model has no second head to answer.
    assert hybrid.event_answers is False
    answering = ["model.event_head_weight=1.0", "model.event_answers=true"]
    assert detector_config(resolve_config(compose_cfg("train", answering)), height=180, width=320).event_answers
    assert not detector_config(resolve_config(compose_cfg("train", ["model=events_only", *answering])),
                               height=180, width=320).event_answers
    with pytest.raises(ConfigError, match=r"model: event_answers needs a hybrid with an event head"):
        build_model(resolve_config(compose_cfg("train", ["model.event_answers=true"])), height=180, width=320)


@pytest.mark.parametrize("override,match", [
    ("loader.batch_size=0", r"loader\.batch_size must be a positive integer, got 0"),
    ("data.window_us=abc", r"data\.window_us must be a positive integer \(microseconds\), got 'abc'"),
    ("trainer.max_steps=-3", r"trainer\.max_steps must be a positive integer or null, got -3"),
    ("trainer.val_every=-1", r"trainer\.val_every must be an integer >= 0"),
    ("data.image_age=-2", r"data\.image_age must be an integer >= 0 \(frames\), got -2"),
    ("data.max_events=0", r"data\.max_events must be a positive integer or null, got 0"),
    ("trainer.ema_decay=1.5", r"trainer\.ema_decay must be a number in \[0, 1\)"),
    ("data.train_image_age_power=-0.5", r"data\.train_image_age_power must be a number >= 0 \(0: ages drawn uniformly\), got -0\.5"),
    ("data.train_image_age_ramp=1.5", r"data\.train_image_age_ramp must be an integer >= 0 \(frames an epoch; 0: the whole range from the start\), got 1\.5"),
    ("model.event_head_weight=-1", r"model\.event_head_weight must be a number >= 0 \(0: no event head\), got -1"),
    ("model.event_answers=2", r"model\.event_answers must be true or false, got 2"),
    ("model.image_stem=vit", r"model\.image_stem must be one of patch, conv, got 'vit'"),
    ("loader.worker_nice=25", r"loader\.worker_nice must be an integer from 0 to 19 \(a Unix nice increment\), got 25"),
    ("data.carry_spans_us=[5,5]", r"data\.carry_spans_us must be a list of increasing positive integers \(microseconds "
                                  r"since the image; \[\]: no spans\), got \[5, 5\]"),
    ("data.carry_spans_us=33333", r"data\.carry_spans_us must be a list of increasing positive integers"),
    ("data.carry_onset=1", r"data\.carry_onset must be true or false, got 1"),
])
def test_bad_values_name_their_key(override, match):
    with pytest.raises(ConfigError, match=match):
        check_values(resolve_config(compose_cfg("train", [override])))


def test_a_run_needs_a_length():
    with pytest.raises(ConfigError, match="trainer.max_steps or trainer.max_epochs"):
        check_values(resolve_config(compose_cfg("train", ["trainer.max_steps=null", "trainer.max_epochs=null"])))
    check_values(resolve_config(compose_cfg("train")))  # the defaults pass


def test_trainer_settings_carry_every_trainer_key_and_decide_the_events_first_phase():
    import dataclasses

    from dagr_lite.config import TrainerSettings, trainer_settings

    assert trainer_settings(compose_cfg("train")).dense_first == 0.5  # the quick recipe's
    cfg = compose_cfg("train", ["trainer.events_first=0.25", "trainer.dense_first=0", "trainer.max_steps=123",
                                "eval.nms_threshold=0.5"])
    settings = trainer_settings(cfg)
    for field in dataclasses.fields(TrainerSettings):
        if field.name in cfg.trainer and field.name != "events_first":
            assert getattr(settings, field.name) == cfg.trainer[field.name], field.name
    assert (settings.image_age, settings.eval_backend) == (cfg.data.image_age, cfg.eval.backend)
    assert (settings.conf_threshold, settings.nms_threshold) == (cfg.eval.conf_threshold, 0.5)
    assert settings.events_first == 0.25 and settings.total_steps(44) == 123
    assert trainer_settings(compose_cfg("train", ["trainer.max_steps=null", "trainer.max_epochs=3"])).total_steps(44) == 132
    # A model with one branch has no events-only phase, nor has a run that starts from other weights.
    assert trainer_settings(compose_cfg("train", ["model=events_only", "trainer.events_first=0.25"])).events_first == 0
    assert trainer_settings(compose_cfg("train", ["model=image_only"])).dense_first == 0
    assert trainer_settings(compose_cfg("train", ["trainer.events_first=0.25", "init_from=x.pt"])).events_first == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.max_steps = 1


def test_what_conf_sets_has_no_second_default_in_the_code():
    """One owner per setting: the code that receives a value conf/ sets takes it as a required
    argument; the horizon's constant is the value conf/data sets."""
    import dataclasses
    import inspect

    from dagr_lite.data import format as fmt
    from dagr_lite.data.augment import TrainAugment
    from dagr_lite.data.dataset import EventEgoHands
    from dagr_lite.data.spec import SampleSpec
    from dagr_lite.engine.schedule import ModelEMA
    from dagr_lite.engine.state import validate, validation_pass
    from dagr_lite.eval.operating import OperatingPoint
    from dagr_lite.eval.score import detections_of, save_pictures, score_entries, score_model
    from dagr_lite.nn.head import postprocess
    from dagr_lite.stream import StreamingDetector

    required = {EventEgoHands.__init__: ("image_age", "window_us", "context_us", "refractory_us", "support_us",
                                         "max_events"),
                StreamingDetector.__init__: ("sample", "operating"),
                validate: ("backend", "conf_threshold", "nms_threshold"),
                validation_pass: ("backend", "conf_threshold", "nms_threshold"),
                score_model: ("backend", "conf_threshold", "nms_threshold"),
                detections_of: ("conf_threshold", "nms_threshold"), score_entries: ("backend",),
                save_pictures: ("conf_threshold", "nms_threshold"),
                postprocess: ("conf_threshold", "nms_threshold"), ModelEMA.__init__: ("decay", "tau")}
    for function, names in required.items():
        parameters = inspect.signature(function).parameters
        assert [n for n in names if parameters[n].default is not inspect.Parameter.empty] == [], function
    for spec in (TrainAugment, SampleSpec):
        assert all(f.default is dataclasses.MISSING for f in dataclasses.fields(spec)), spec
    assert [f.name for f in dataclasses.fields(OperatingPoint) if f.default is not dataclasses.MISSING] == \
        ["f1", "precision", "recall", "chosen_on"]  # what was measured, absent from a point given by hand
    assert compose_cfg("train").data.window_us == fmt.DEFAULT_WINDOW_US


def test_a_detector_answers_only_with_the_thresholds_given():
    from dagr_lite.nn.detector import Detector
    from tests.models import small_detector_config

    model = Detector(small_detector_config()).eval()
    with pytest.raises(TypeError, match=r"needs conf_threshold= and nms_threshold= \(eval\.\* in conf/\)"):
        model(None)


def test_a_trainer_key_the_loop_does_not_read_is_refused():
    with pytest.raises(ConfigError, match="trainer.nonexistent is not a training setting; the trainer reads amp, "):
        check_values(compose_cfg("train", ["+trainer.nonexistent=3"]))


def test_an_image_age_longer_than_every_video_is_refused_not_scored_minus_one():
    cfg = resolve_config(compose_cfg("train", ["data.image_age=1000"]))
    with pytest.raises(ConfigError, match=r"\[valid\]: no sample at image age 1000: its videos have 60 to 60 frames"):
        build_dataset(cfg, "valid", train=False, with_image=True)


@pytest.mark.parametrize("name", ["evaluate", "sweep"])
def test_evaluation_reads_every_sample_key_from_the_checkpoint_unless_given(name, tmp_path):
    """Each key of a sample is null in evaluate's and sweep's ``data`` (the checkpoint's value), so
    no key of conf/data's training defaults overrides what a model was trained with."""
    from dagr_lite.data.spec import SampleSpec

    cfg = compose_cfg(name, [f"ckpt={tmp_path / 'last.pt'}"] if name == "evaluate" else ["ckpt=[a.pt]"])
    assert {key: cfg.data.get(key) for key in SampleSpec.keys()} == dict.fromkeys(SampleSpec.keys())
