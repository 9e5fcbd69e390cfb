"""A user's mistake is one line and exit status 1; a bug keeps its traceback."""
from __future__ import annotations

import time
from pathlib import Path

import pytest

from dagr_lite.apps.cli import user_errors
from dagr_lite.config import ConfigError
from dagr_lite.errors import UserError

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("error", [UserError("sample window_us must be a positive integer, got -5"),
                                   ConfigError("loader.batch_size must be a positive integer, got 0"),
                                   FileNotFoundError("ckpt.pt: checkpoint file is missing")])
def test_a_users_mistake_is_one_line(error, capsys, monkeypatch):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with pytest.raises(SystemExit) as stopped:
        with user_errors():
            raise error
    assert stopped.value.code == 1
    assert capsys.readouterr().err == f"error: {error}\n"


@pytest.mark.parametrize("error", [ValueError("too many values to unpack"), KeyError("ema"), TypeError("x")])
def test_a_bug_keeps_its_traceback(error, capsys):
    with pytest.raises(type(error)):
        with user_errors():
            raise error
    assert capsys.readouterr().err == ""


def test_ctrl_c_is_one_line_and_exit_status_130(capsys):
    with pytest.raises(SystemExit) as stopped:
        with user_errors():
            raise KeyboardInterrupt
    assert stopped.value.code == 130 and capsys.readouterr().err == "interrupted\n"


def test_the_sweep_without_out_is_a_users_mistake_not_hydras_trace(tmp_path):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", f"ckpt=[{tmp_path / 'none.pt'}]"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 1 and run.stderr.strip() == f"error: {tmp_path / 'none.pt'}: checkpoint file is missing"
    assert not (tmp_path / "runs").exists()


def test_a_config_group_the_command_does_not_compose_is_named():
    from dagr_lite.apps.cli import composition_problem

    assert composition_problem("evaluate", ["ckpt=x.pt", "model=events_only"]) == (
        "model=events_only: conf/evaluate.yaml takes no model option; the model comes from the checkpoint (ckpt=)")
    assert composition_problem("sweep", ["ckpt=[x.pt]", "optim=sgd"]) == "optim=sgd: conf/sweep.yaml takes no optim option"
    assert composition_problem("train", ["model=events_only"]) is None


def test_a_list_without_brackets_is_named_with_the_brackets_not_hydras_multirun():
    from dagr_lite.apps.cli import composition_problem

    assert composition_problem("sweep", ["ckpt=a.pt,b.pt"]) == (
        "ckpt=a.pt,b.pt: a list is written in brackets, ckpt=[a.pt,b.pt] (a text with a comma: in quotes, "
        "ckpt=\"'a.pt,b.pt'\")")


def test_a_key_added_with_a_plus_is_refused_among_settings_and_allowed_among_named_entries():
    from dagr_lite.apps.cli import composition_problem
    for override in ("+loader.batchsize=8", "+sed=1", "++trainer.max_minute=5", "+nothing.here=1", "+model.sizes.s.x=1"):
        key = override.lstrip("+").split("=")[0]
        assert composition_problem("train", [override]) == (
            f"+{key}: no such setting in conf/train.yaml; a setting added with '+' would be read by nothing "
            "(`--cfg job` prints every setting)")
    # a size of one's own, chosen by name: model.sizes holds named entries only
    assert composition_problem("train", ["+model.sizes.l={image_width:32,event_channels:[24,48,72,96],head_hidden:128}",
                                         "model.size=l"]) is None
    assert composition_problem("train", ["+model.sizes.l={image_width:32,event_channels:[24,48,72,96],head_hidden:128}",
                                         "model.sizes.l.head_hidden=64", "model.size=l"]) is None  # into what + adds
    assert composition_problem("train", ["++trainer.max_minutes=5"]) is None  # there already: ++ sets it
    assert "already" in composition_problem("train", ["+trainer.max_minutes=5"])  # Hydra's own refusal


@pytest.mark.parametrize("name, groups", [("train", ["dataset", "model", "optim", "data", "loader", "eval", "recipe"]),
                                          ("evaluate", ["dataset", "data", "loader", "eval"]),
                                          ("sweep", ["dataset", "data", "loader", "eval"]),
                                          ("demo", ["dataset", "operating"]), ("detect", ["operating"])])
def test_help_lists_the_groups_the_command_composes(name, groups):
    from omegaconf import OmegaConf

    from dagr_lite.apps.cli import command_help
    from dagr_lite.config import compose_config
    text = command_help(name, ["loader.batch_size=3"] if "loader" in groups else [])
    listed = text.split("Config groups")[1].split("\n\n")[0].splitlines()[1:]
    assert [line.split(":")[0].strip() for line in listed] == groups
    assert "  dataset: custom, ego, stub, v1, v2, v3, v4, v5, v6" in listed or "dataset" not in groups
    assert text.splitlines()[0].startswith("python ")  # the usage line of conf/<name>.yaml
    settings = OmegaConf.create(text.split("Hydra's flags):\n", 1)[1])
    expected = compose_config(name, ["loader.batch_size=3"] if "loader" in groups else [])
    assert OmegaConf.to_container(settings) == OmegaConf.to_container(expected)  # overrides given with --help apply


def test_help_says_what_each_key_means_where_it_is_first_set(tmp_path):
    from dagr_lite.apps.cli import command_help, key_comments, with_comments
    text = command_help("train", ["dataset=ego"])
    lines = text.splitlines()
    at = lines.index(next(line for line in lines if line.startswith("  max_minutes: 13.0 ")))
    assert lines[at].endswith("# wall-clock cap; the run stops cleanly (and saves) when it is reached")  # train.yaml's
    schedule = "\n".join(lines[lines.index(next(line for line in lines if line.startswith("  schedule_by: time"))):][:4])
    assert "(whichever is further along" in schedule and "1,760" not in schedule  # not the recipe's words on it
    assert "  crop: 0.5" in text and "# < 1: each sample is cut" in text  # data/default.yaml's, the recipe's value
    # Only the files the chosen options compose, their bases first: no other dataset's word on root, the
    # hybrid's meaning of a key events_only sets, a key without a comment left bare.
    other = command_help("train", ["dataset=v6", "model=events_only"]).splitlines()
    assert "  root: ${eventegohands_root:v6}" in other
    assert next(line for line in other if line.startswith("    radius: 3.0")).endswith("# pixels")
    assert "# > 0: a carry branch of this width" in next(line for line in other if line.startswith("  carry_width: 0"))
    # A hand-made case: nesting, a comment carried on, a later file's comment on a described key ignored.
    first, second = tmp_path / "a.yaml", tmp_path / "b.yaml"
    first.write_text("# a header\nouter:\n  inner: 1   # what inner is,\n              # said on two lines\n"
                     "  bare: 2\nlist:   # items\n- 3\n")
    second.write_text("inner: 5  # another file's word on it\n          # and its second line\nnew: 6  # only here\n")
    comments = key_comments([(first, ""), (second, "outer")])
    assert comments == {"outer.inner": "what inner is, said on two lines", "list": "items", "outer.new": "only here"}
    assert with_comments("outer:\n  inner: 1\n  bare: 2", comments, width=60).splitlines() == [
        "outer:", "  inner: 1" + " " * 16 + "# what inner is, said on two lines", "  bare: 2"]


def test_help_runs_as_a_command_and_names_a_bad_override(tmp_path):
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", "--help"], capture_output=True, text=True,
                         cwd=tmp_path, timeout=300)
    assert run.returncode == 0 and "\n  eval: default\n" in run.stdout and "\n  model: " not in run.stdout
    run = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", "--help", "model=hybrid"], capture_output=True,
                         text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 1 and run.stderr.startswith("error: model=hybrid: conf/sweep.yaml takes no model option")
    run = subprocess.run([sys.executable, "-m", "dagr_lite.apps.sweep", "--help", "--cfg", "job"], capture_output=True,
                         text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 0 and "powered by Hydra" in run.stdout  # beside another flag: Hydra's own help
    assert not (tmp_path / "runs").exists()


def test_a_failed_command_removes_only_a_folder_it_made(tmp_path):
    """detect's Hydra folder is the current one; a run_dir the user made stays too, empty or not."""
    import subprocess
    import sys

    here = tmp_path / "empty"
    here.mkdir()
    run = subprocess.run([sys.executable, str(ROOT / "detect.py"), f"ckpt={tmp_path / 'none.pt'}", "input=none.raw"],
                         capture_output=True, text=True, cwd=here, timeout=300)
    assert run.returncode == 1 and run.stderr.startswith("error: ")
    assert here.is_dir()  # the current folder, empty, was not removed
    mine = tmp_path / "mine"
    mine.mkdir()
    time.sleep(1.5)  # the folder is older than the command
    run = subprocess.run([sys.executable, str(ROOT / "evaluate.py"), f"ckpt={tmp_path / 'none.pt'}", f"run_dir={mine}"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 1 and "checkpoint file is missing" in run.stderr
    assert mine.is_dir()
    run = subprocess.run([sys.executable, str(ROOT / "evaluate.py"), f"ckpt={tmp_path / 'none.pt'}",
                          f"run_dir={tmp_path / 'made'}"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 1 and not (tmp_path / "made").exists()  # the folder the command made is gone
