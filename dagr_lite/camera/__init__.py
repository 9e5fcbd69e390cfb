"""Real cameras: recordings of any event camera and live UDP streams in, detections out.

``recording`` reads AEDAT4, EVT2/EVT3, DAT, ES, CSV (through faery) and this package's h5 layout in
time-ordered chunks; ``aedat`` writes AEDAT4 with a frame track; ``sensor`` maps a camera's sensor
to the model's input and boxes back; ``udp`` receives live streams; ``detect`` runs a checkpoint
over any of them; ``export`` writes a dataset to the other formats; ``render`` draws what it saw.
"""
