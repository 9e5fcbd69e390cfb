"""A sensor's crop, rotation, flips and scale, against drawing boxes into frames and reading them back."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from dagr_lite.camera.sensor import Sensor, SensorError, fit_sensor, fitting_settings


@pytest.mark.parametrize(("rotate", "flip_x", "flip_y", "scale"),
                         list(itertools.product((0, 90, 180, 270), (False, True), (False, True), (1, 2))))
def test_boxes_go_back_to_where_the_sensor_saw_them(rotate, flip_x, flip_y, scale):
    """A box filled into a sensor frame, mapped by :meth:`Sensor.frame`, is found at the model's box
    whose :meth:`Sensor.boxes_to_sensor` is the original box; its corner events land inside it."""
    sensor = Sensor((40, 24), crop=(4, 2, 32, 20), scale=scale, rotate=rotate, flip_x=flip_x, flip_y=flip_y)
    rng = np.random.default_rng(rotate + 2 * flip_x + 4 * flip_y + 8 * scale)
    for _ in range(6):
        x1, y1 = 4 + 2 * rng.integers(0, 8), 2 + 2 * rng.integers(0, 5)
        x2, y2 = x1 + 2 * rng.integers(1, 4), y1 + 2 * rng.integers(1, 4)
        image = np.zeros((24, 40, 1), np.uint8)
        image[y1:y2, x1:x2] = 255
        ys, xs = np.nonzero(sensor.frame(image)[..., 0])
        model_box = np.array([[xs.min(), ys.min(), xs.max() + 1, ys.max() + 1]])
        np.testing.assert_allclose(sensor.boxes_to_sensor(model_box)[0], [x1, y1, x2, y2])
        corners = sensor.events({"x": np.array([x1, x2 - 1, x1, 0]), "y": np.array([y1, y2 - 1, y2 - 1, 0]),
                                 "t": np.arange(4), "p": np.ones(4)})
        assert corners["t"].tolist() == [0, 1, 2]  # the event at (0, 0) lies outside the crop
        assert np.all((corners["x"] >= model_box[0, 0]) & (corners["x"] < model_box[0, 2]))
        assert np.all((corners["y"] >= model_box[0, 1]) & (corners["y"] < model_box[0, 3]))
    assert sensor.frame(np.zeros((24, 40, 3), np.uint8)).shape[1::-1] == sensor.output_size


def test_scaling_bins_pixels_as_the_dataset_versions_were_made():
    from dagr_lite.synth.video import downscale_area

    image = np.random.default_rng(0).integers(0, 256, (36, 64, 3), dtype=np.uint8)
    expected = np.clip(np.round(downscale_area(image, 4)), 0, 255).astype(np.uint8)
    np.testing.assert_array_equal(Sensor((64, 36), scale=4).frame(image), expected)
    events = Sensor((64, 36), scale=4).events({"x": np.array([0, 3, 4, 63]), "y": np.array([0, 3, 4, 35]),
                                               "t": np.arange(4), "p": np.zeros(4)})
    assert events["x"].tolist() == [0, 0, 1, 15] and events["y"].tolist() == [0, 0, 1, 8]


def test_a_sensor_that_does_not_fit_the_model_is_refused_with_a_setting_that_would():
    assert fitting_settings((640, 480), (320, 180)) == "sensor.scale=2 sensor.crop=[0,60,640,360]"
    assert fitting_settings((1280, 720), (320, 180)) == "sensor.scale=4"
    with pytest.raises(SensorError, match=r"the 640x480 sensor gives 640x480 .* the model reads 320x180; "
                                          r"sensor.scale=2 sensor.crop=\[0,60,640,360\] fits"):
        fit_sensor(Sensor((640, 480)), (320, 180))
    with pytest.raises(SensorError, match="the sensor is smaller than the model's input.*sensor.model_size=sensor"):
        fit_sensor(Sensor((160, 120)), (320, 180))
    fit_sensor(Sensor((640, 480), crop=(0, 60, 640, 360), scale=2), (320, 180))
    # a camera mounted on its side: the crop is taken before the rotation, so it is tall
    hint = fitting_settings((480, 640), (320, 180), rotate=90)
    assert hint == "sensor.scale=2 sensor.crop=[60,0,360,640]"
    with pytest.raises(SensorError, match=r"sensor.scale=2 sensor.crop=\[60,0,360,640\] fits"):
        fit_sensor(Sensor((480, 640), rotate=90), (320, 180))
    fit_sensor(Sensor((480, 640), crop=(60, 0, 360, 640), scale=2, rotate=90), (320, 180))  # the hint fits
    # the model's size is the whole sensor's: a crop given is what does not fit, and the hint takes it away
    with pytest.raises(SensorError, match=r"gives 300x160 .* sensor.scale=1 sensor.crop=null fits"):
        fit_sensor(Sensor((320, 180), crop=(10, 10, 300, 160)), (320, 180))
    for bad, message in (({"crop": (600, 0, 100, 10)}, "inside the 640x480 sensor"),
                         ({"scale": 3}, "sensor.scale=3 must divide the cropped 640x480"),
                         ({"rotate": 45}, "sensor.rotate=45 must be one of")):
        with pytest.raises(SensorError, match=message):
            Sensor((640, 480), **bad)
