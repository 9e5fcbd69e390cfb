"""The README runs as written: its Python blocks run (placeholders such as ``<run>`` filled in), each
command of its command table and its command blocks is composed with its own overrides (a key or
option the code does not have fails), commands that take options show them in ``--help``, and the
quick commands run for real."""
from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from dagr_lite.config import compose_config

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()

# Programs whose options are Hydra overrides, and the config each composes.
HYDRA = {"train.py": "train", "evaluate.py": "evaluate", "detect.py": "detect", "dagr_lite.apps.sweep": "sweep",
         "dagr_lite.apps.demo": "demo"}
# The README's placeholders, and what a test run reads in their place.
PLACEHOLDER = re.compile(r"^(CKPT|FILE|ROOT|REC|DIR|PATH|RUN|HOST|A|B)\b")


def blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README, flags=re.S)


def commands() -> list[str]:
    """Every command of the README: its command table's first column and its bash blocks' lines."""
    table = [cell.replace("\\|", "|") for cell in re.findall(r"^\| `(python [^`]*)`", README, flags=re.M)]
    table = [part.strip() for cell in table for part in cell.split(" / ")]  # "A / B": two commands in one cell
    lines = []
    for block in blocks("bash"):
        for line in block.replace("\\\n", " ").splitlines():
            line = line.split("  #")[0].strip()
            if line and not line.startswith("#"):
                lines += [part.strip() for part in line.split("&&")]
    ours = ("train.py", "evaluate.py", "detect.py", "dagr_lite.", "data_stubs/", "benchmarks/")
    return [c for c in table + lines if c.startswith(("python", "torchrun")) and any(o in c for o in ours)]


def program_and_arguments(command: str) -> tuple[str, list[str]]:
    """``("train.py" | "dagr_lite.apps.sweep" | ..., arguments)`` of a command: optional parts
    ``[...]`` are taken, alternatives ``a | b`` give their first."""
    command = re.sub(r"\[([^\[\]]*=[^\[\]]*|--[^\[\]]*)\]", r"\1", command)  # [k=v], [--o v]: taken; lists stay
    command = re.sub(r" \| [^ \]]+", "", command)  # [model=a | model=b] -> model=a
    command = re.sub(r"(\S)\|\S+", r"\1", command)  # input=FILE|udp://... -> input=FILE
    words = shlex.split(command)
    if words[0] == "torchrun":
        words = ["python"] + words[next(i for i, w in enumerate(words) if w.endswith(".py")):]
    if words[1] == "-m":
        return words[2], words[3:]
    return words[1], words[2:]


def test_the_readme_holds_commands_of_every_kind():
    programs = {program_and_arguments(c)[0] for c in commands()}
    assert set(HYDRA) <= programs
    assert {"dagr_lite.data.check", "dagr_lite.apps.export", "dagr_lite.synth.build", "dagr_lite.apps.label",
            "dagr_lite.apps.versions", "dagr_lite.apps.stats", "data_stubs/generate.py"} <= programs


@pytest.mark.parametrize("command", [c for c in commands() if program_and_arguments(c)[0] in HYDRA])
def test_every_hydra_command_of_the_readme_composes_with_its_overrides(command):
    program, arguments = program_and_arguments(command)
    overrides = [a for a in arguments if "=" in a and not a.startswith("-") and not a.startswith("key=")]
    cfg = compose_config(HYDRA[program], overrides)  # an unknown key, group or option raises here
    for override in overrides:
        key, value = override.split("=", 1)
        if key not in ("dataset", "model", "recipe", "optim"):  # group choices select a file
            assert OmegaConf.select(cfg, key, default="<absent>") != "<absent>", override


OTHERS = sorted({program_and_arguments(c)[0] for c in commands()} - set(HYDRA))


@pytest.fixture(scope="module")
def helps() -> dict[str, tuple[int, str, str]]:
    """``{program: (return code, stdout, stderr)}`` of every other program's ``--help``, the
    processes run side by side (each spends its time importing)."""
    running = {}
    for program in OTHERS:
        target = ["-m", program] if not program.endswith(".py") else [str(ROOT / program)]
        running[program] = subprocess.Popen([sys.executable, *target, "--help"], cwd=ROOT, text=True,
                                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    done = {}
    for program, process in running.items():
        out, err = process.communicate(timeout=120)
        done[program] = (process.returncode, out, err)
    return done


@pytest.mark.parametrize("program", OTHERS)
def test_every_other_command_shows_the_options_the_readme_gives_it(program, helps):
    code, text, err = helps[program]
    assert code == 0, err
    for command in commands():
        name, arguments = program_and_arguments(command)
        if name == program:
            for option in (a for a in arguments if a.startswith("--")):
                assert option.split("=")[0] in text, (command, option)


def test_the_python_blocks_run_as_written(trained_checkpoints):
    """The streaming detector's block as written (the stub's test video; the checkpoint path filled in),
    and the graph block."""
    stream_block, graph_block = blocks("python")
    ckpt = trained_checkpoints["hybrid"]
    namespace = {}
    exec(stream_block.replace("runs/train/<run>/checkpoints/best.pt", str(ckpt)), namespace)
    answer, rec = namespace["answer"], namespace["rec"]
    assert answer["boxes"].shape[1:] == (4,) and answer["t_us"] == rec.events_between(0, rec.frame_times[1])["t"][-1]
    assert namespace["detector"].operating.nms_iou < 0.5  # the checkpoint's operating point

    rng = np.random.default_rng(0)
    x, y = rng.integers(0, 320, 300), rng.integers(0, 180, 300)
    t, p = np.sort(rng.integers(0, 30_000, 300)), rng.integers(0, 2, 300)
    events = torch.tensor(np.stack([x[:300], y[:300], t[:300], p[:300]], 1), dtype=torch.float32)
    namespace = {"events": events, "batch": torch.zeros(300, dtype=torch.long), "features": torch.randn(300, 4),
                 "new_pos": torch.tensor(np.stack([x[:50], y[:50], 5e-4 * t[:50]], 1), dtype=torch.float64)}
    exec(graph_block, namespace)
    assert namespace["h"].shape == (300, 32) and namespace["edge_index"].shape[0] == 2


def test_the_quick_commands_run(trained_checkpoints, tmp_path):
    from dagr_lite.synth.stub import stub_root

    check = subprocess.run([sys.executable, "-m", "dagr_lite.data.check", str(stub_root())], cwd=ROOT,
                           capture_output=True, text=True, timeout=300)
    assert check.returncode == 0, check.stderr
    evaluate = subprocess.run([sys.executable, "evaluate.py", f"ckpt={trained_checkpoints['events_only']}",
                               "split=test", f"run_dir={tmp_path / 'eval'}", "loader.num_workers=0"],
                              cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert evaluate.returncode == 0, evaluate.stderr
    assert (tmp_path / "eval" / "metrics.json").is_file()


def test_the_version_table_is_the_builders():
    from dagr_lite.synth.build import VERSIONS
    from dagr_lite.synth.egohands import EGOHANDS_HEIGHT, EGOHANDS_WIDTH

    rows = re.findall(r"^\| (v\d) \| (\d+) \| (\d+) \| (\d+)x(\d+) \| (\w+) \|$", README, flags=re.M)
    assert sorted(row[0] for row in rows) == sorted(VERSIONS)
    for version, upsample, scale, width, height, dvs_model in rows:
        made = VERSIONS[version]
        assert (int(upsample), int(scale), dvs_model) == (made["upsample"], made["scale"], made["dvs_model"])
        assert (int(width), int(height)) == (EGOHANDS_WIDTH // made["scale"], EGOHANDS_HEIGHT // made["scale"])


def test_the_stub_root_the_readme_names_is_the_one_made():
    from dagr_lite.synth.stub import STUB_VERSION

    named = set(re.findall(r"stub-v(\d+)", README))
    assert named == {str(STUB_VERSION)}
