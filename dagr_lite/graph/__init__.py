"""Event graphs: the causal radius graph (batch and streaming), voxel pooling, dense maps."""
from dagr_lite.graph.pool import PooledGraph, to_dense, voxel_max_pool
from dagr_lite.graph.radius import event_graph, radius_graph
from dagr_lite.graph.streaming import StreamingGraph

__all__ = ["PooledGraph", "StreamingGraph", "event_graph", "radius_graph", "to_dense", "voxel_max_pool"]
