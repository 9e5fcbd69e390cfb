"""Event graphs: the causal radius graph (batch and streaming), voxel pooling, dense maps."""
from dagr_lite.graph.radius import radius_graph

__all__ = ["radius_graph"]
