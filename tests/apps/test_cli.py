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
