from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from dagr_lite.config import ConfigError, check_values, compose_config
from dagr_lite.data.collate import collate
from dagr_lite.engine.checkpoint import CHECKPOINT_FORMAT
from dagr_lite.engine.starting import graph_note, start_from, start_weights
from dagr_lite.engine.train import train
from dagr_lite.nn.detector import Detector
from dagr_lite.nn.warm_start import warm_start, widen
from dagr_lite.synth.stub import stub_root
from tests.models import small_detector_config
from tests.settings import SAMPLE, sample_set

SIZES = dict(image_width=8, event_channels=(8, 8, 8, 8), head_hidden=16)
GRAPH = dict(SIZES, event_dense=0)  # GCN pooled stages: image features join every stage


def test_widen_puts_the_source_first_and_zeros_after_it():
    source = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    wide = widen(source, torch.Size([4, 3]))
    assert torch.equal(wide, torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]))
    assert torch.equal(widen(source, torch.Size([2, 5]))[:, 3:], torch.zeros(2, 2))
    assert widen(source, torch.Size([3, 4])) is None  # two dimensions differ
    assert widen(source, torch.Size([1, 3])) is None  # the source is the larger
    assert widen(source, torch.Size([2, 3, 1])) is None
    assert widen(source, torch.Size([4, 3]), dim=1) is None  # not the dimension asked for
    assert torch.equal(widen(source, torch.Size([4, 3]), dim=0), widen(source, torch.Size([4, 3])))


@pytest.mark.parametrize(("directional", "event_dense"), [(False, 0), (True, 0), (False, 4)])
def test_an_events_only_branch_started_in_a_hybrid_computes_the_same_maps_whatever_the_image(directional,
                                                                                             event_dense):
    torch.manual_seed(0)
    sizes = dict(SIZES, directional=directional, event_dense=event_dense)
    events_only = Detector(small_detector_config(variant="events_only", **sizes)).eval()
    # the same maps need the same graph (the events-only model's default is smaller than the hybrid's)
    hybrid = Detector(small_detector_config(graph=events_only.cfg.graph, **sizes)).eval()
    report = warm_start(hybrid, events_only.state_dict())
    # every first block of a GCN stage reads the node's time (stage 0) and image channels besides the source's
    # inputs (there, with as many channels in as out, the source's skip is the identity: widened from it); a
    # directional first stage's offset weights are widened along their input dimension too; dense pooled
    # stages read no image and are copied
    assert sorted(report["widened"]) == sorted([f"events.stages.{s}.0.{layer}.weight" for s in range(1 if event_dense else 4)
                                                for layer in ("conv", "skip")]
                                               + ["events.stages.0.0.conv.weight_offsets"] * directional)
    # layers reading more inputs outside the event branch, or only the hybrid's, keep their own weights
    # (the head's late layers read the image's age and image towers besides the recency maps; the image
    # towers and their age gates are the hybrid's, as is its carry branch)
    wider = ("image.", "to_nodes.", "fuse.", "head.stems.", "head.cls_late.", "head.reg_late.", "head.gates.",
             "head.image_", "carry.")
    assert all(name.startswith(wider) or name.endswith("num_batches_tracked") for name in report["kept"])
    dataset = sample_set(stub_root(), "valid", image_age=3, window_us=15_000)
    batch = collate([dataset[i] for i in (5, 40)])
    with torch.no_grad():
        expected = events_only.events(batch.events, batch.batch_index, len(batch))
        for images in (batch.images, torch.zeros_like(batch.images), torch.full_like(batch.images, 255)):
            sampler = hybrid.node_sampler(hybrid.node_maps(hybrid.image(images)))
            maps = hybrid.events(batch.events, batch.batch_index, len(batch), image_sampler=sampler)
            for got, want in zip(maps, expected, strict=True):
                torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
        # the reference is not trivially equal: the hybrid's own initialisation gives other maps
        fresh = Detector(small_detector_config(**SIZES)).eval()
        sampler = fresh.node_sampler(fresh.node_maps(fresh.image(batch.images)))
        other = fresh.events(batch.events, batch.batch_index, len(batch), image_sampler=sampler)
    assert not torch.allclose(other[0], expected[0])


def test_same_shapes_are_copied_and_only_the_event_branch_is_widened():
    torch.manual_seed(0)
    source = Detector(small_detector_config(**GRAPH))
    target = Detector(small_detector_config(**GRAPH))
    report = warm_start(target, source.state_dict())
    assert report["widened"] == [] and all(name.endswith("num_batches_tracked") for name in report["kept"])
    for name, value in source.state_dict().items():
        assert torch.equal(target.state_dict()[name], value)
    # a head reading more channels is not widened: its inputs are not laid out source-first
    wider_image = Detector(small_detector_config(**{**GRAPH, "image_width": 16}))
    report = warm_start(wider_image, source.state_dict())
    assert report["widened"] == [] and any(name.startswith("head.stems.") for name in report["kept"])
    # a wider event branch (more outputs per stage, as in size m) is not widened: it would zero whole channels
    wider_events = Detector(small_detector_config(**{**GRAPH, "event_channels": (12, 12, 12, 12)}))
    report = warm_start(wider_events, source.state_dict())
    assert report["widened"] == [] and "events.stages.1.0.norm.weight" in report["kept"]


def _save(path, model):
    torch.save({"format": CHECKPOINT_FORMAT, "model": model.state_dict(),
                "ema": {"module": model.state_dict(), "updates": 0}, "detector": model.cfg.as_dict(),
                "config": {"model": {"name": "events_only"}, "data": {"image_age": 1, **SAMPLE}}}, path)


def test_start_from_reads_a_checkpoint_and_refuses_what_cannot_start_a_run(tmp_path):
    torch.manual_seed(0)
    events_only = Detector(small_detector_config(variant="events_only", **GRAPH))
    _save(tmp_path / "ev.pt", events_only)
    hybrid = Detector(small_detector_config(**GRAPH))
    report = start_from(hybrid, tmp_path / "ev.pt", verbose=False)
    assert len(report["widened"]) == 8
    assert torch.equal(hybrid.state_dict()["events.stages.1.0.norm.weight"],
                       events_only.state_dict()["events.stages.1.0.norm.weight"])
    foreign = torch.nn.Sequential(torch.nn.Linear(3, 5))
    torch.save({"format": CHECKPOINT_FORMAT, "model": foreign.state_dict(), "ema": None}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match=r"foreign\.pt: its model, sample or operating point cannot be read"):
        start_from(hybrid, tmp_path / "foreign.pt")
    saved = torch.load(tmp_path / "ev.pt", weights_only=True)
    torch.save({**saved, "model": foreign.state_dict(), "ema": {"module": foreign.state_dict(), "updates": 0}},
               tmp_path / "unfit.pt")
    with pytest.raises(ValueError, match=r"no weight of that checkpoint \(events_only\) fits this model"):
        start_from(hybrid, tmp_path / "unfit.pt")
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        start_from(hybrid, tmp_path / "missing.pt")


def test_a_start_from_another_graph_says_so_and_how_to_keep_the_checkpoints(tmp_path, capsys):
    events_only = Detector(small_detector_config(variant="events_only", **GRAPH))
    _save(tmp_path / "ev.pt", events_only)
    start_from(Detector(small_detector_config(**GRAPH)), tmp_path / "ev.pt")
    said = capsys.readouterr().out
    assert ("the checkpoint's event graph (radius 3 px, 8 neighbours, beta 0.0005) is not this run's (radius 5, 16, "
            "beta 0.0005)") in said
    assert "model.graph.radius=3 model.graph.max_neighbors=8 model.graph.beta=0.0005 keep its own" in said
    start_from(Detector(small_detector_config(graph=events_only.cfg.graph, **GRAPH)), tmp_path / "ev.pt")
    assert "event graph" not in capsys.readouterr().out  # the same graph: nothing to say
    assert graph_note(None, events_only.cfg.graph) is None and graph_note(events_only.cfg.graph, None) is None


def test_init_from_starts_a_new_run_only():
    assert start_weights(OmegaConf.create({"init_from": None, "resume": None}), None) is None
    assert start_weights(OmegaConf.create({"init_from": "ev.pt", "resume": None}), None) == "ev.pt"
    # restarted in its own folder (torchrun), the run continues from its own last.pt
    assert start_weights(OmegaConf.create({"init_from": "ev.pt", "resume": None}), Path("run/last.pt")) is None
    with pytest.raises(ConfigError, match="init_from=ev.pt .* resume=run/last.pt .* give one of them"):
        check_values(OmegaConf.create({"init_from": "ev.pt", "resume": "run/last.pt"}))
    check_values(OmegaConf.create({"init_from": "ev.pt", "resume": None}))


@pytest.mark.parametrize("key", ["init_from", "resume"])
def test_a_missing_start_checkpoint_is_refused_before_the_run_folder_is_made(tmp_path, key):
    cfg = compose_config("train", [f"run_dir={tmp_path / 'run'}", f"{key}={tmp_path / 'nope.pt'}"])
    with pytest.raises(FileNotFoundError, match=f"{key}=.*nope.pt: checkpoint file is missing"):
        train(cfg)
    assert not (tmp_path / "run").exists()
