"""The EventEgoHands data layer: layout, reading, writing, validation, samples and batches."""
from dagr_lite.data.augment import TrainAugment, hflip, zoom_translate
from dagr_lite.data.collate import Batch, collate
from dagr_lite.data.dataset import EventEgoHands, Sample
from dagr_lite.data.errors import DatasetFormatError, Problem
from dagr_lite.data.events import EventFile
from dagr_lite.data.frames import read_frame
from dagr_lite.data.labels import read_labels

__all__ = ["Batch", "DatasetFormatError", "EventEgoHands", "EventFile", "Problem", "Sample", "TrainAugment",
           "collate", "hflip", "read_frame", "read_labels", "zoom_translate"]
