"""Applications: thin entry points over the library, the top layer of the package.

``sweep`` (quality against image age), ``demo`` (the streaming detector over one recording, as an
MP4), ``detect`` (``python detect.py``), ``export`` (a dataset to camera formats), ``stats`` and
``recording_stats`` (dataset and recording statistics), ``label`` (labels for every frame) and
``versions`` (the dataset-version experiment); ``cli`` holds what the commands share.
"""
