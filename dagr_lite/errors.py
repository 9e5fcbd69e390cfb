"""The error a user's mistake raises.

:class:`UserError` is raised where what the user gave is wrong: a value, a file, a folder, an
option, a checkpoint, the input of the streaming detector. Its message names the key, file or
value and what was expected. The commands print it as one line, ``error: <message>``, and exit
with status 1 (:mod:`dagr_lite.apps.cli`); any other exception is a bug and keeps its traceback.
It is a ``ValueError``, so code that catches those catches it too.
"""
from __future__ import annotations


class UserError(ValueError):
    """A mistake in what the user gave; the message says what and what was expected."""
