"""``python detect.py`` refuses a setting of the wrong type by key and value, before it reads anything."""
from __future__ import annotations

import pytest

from dagr_lite.apps.detect import detect
from dagr_lite.config import ConfigError, compose_config


@pytest.mark.parametrize(("override", "message"), [
    ("sensor.flip_x=no", "sensor.flip_x must be true or false, got 'no'"),
    ("sensor.flip_y=1", "sensor.flip_y must be true or false, got 1"),
    ("sensor.scale=2.5", "sensor.scale must be a positive integer (pixels binned scale x scale), got 2.5"),
    ("sensor.crop=[0,0,100]", "sensor.crop must be [x0, y0, width, height], four integers"),
    ("sensor.crop=[0,0.5,100,100]", "sensor.crop must be [x0, y0, width, height], four integers"),
    ("sensor.crop=abc", "sensor.crop must be [x0, y0, width, height], four integers"),
    ("sensor.rotate=45", "sensor.rotate must be one of 0, 90, 180, 270"),
    ("sensor.size=[640]", "sensor.size must be [width, height], two positive integers"),
    ("rate_hz=abc", "rate_hz must be a positive number"),
    ("seconds=-1", "seconds must be a positive number of seconds or null"),
    ("operating.score=high", "operating.score must be a number in [0, 1], or null"),
    ("order=maybe", "order must be sort or refuse"),
])
def test_a_setting_of_the_wrong_type_is_refused_by_key_and_value(override, message, tmp_path):
    cfg = compose_config("detect", ["ckpt=missing.pt", f"input={tmp_path / 'missing.csv'}", override])
    with pytest.raises(ConfigError) as refused:
        detect(cfg)
    assert str(refused.value).startswith(message)
