"""A user's mistake is one line and exit status 1; a bug keeps its traceback."""
from __future__ import annotations

import pytest

from dagr_lite.apps.cli import user_errors
from dagr_lite.config import ConfigError
from dagr_lite.errors import UserError


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
