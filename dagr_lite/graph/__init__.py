"""Event graphs: the causal radius graph (batch and streaming), voxel pooling, dense maps."""
from dagr_lite.graph.radius import radius_graph
from dagr_lite.graph.streaming import StreamingGraph

__all__ = ["StreamingGraph", "radius_graph"]
