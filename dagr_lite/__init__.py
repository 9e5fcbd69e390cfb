"""dagr_lite: hybrid event + RGB hand detection of the DAGr family, in plain PyTorch."""

__version__ = "0.1.0"
